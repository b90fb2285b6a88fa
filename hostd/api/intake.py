"""A client's requests as its transport reads them, the same on every transport.

The Unix socket (server.py) and the WebSocket (web/websocket.py) each read whole
messages and hand every one to their client's `Intake`:

- A message that is not a request, or a batch that cannot run, is answered
  at once and nothing runs.
- At most `max_inflight` requests run at once, counting each request of a
  batch: the reader waits for slots before it reads on, so a client that
  floods waits, and nobody else does.
- A lone realtime request (`rpc.is_immediate`) with none of the client's
  earlier requests under way runs in the reader itself, without a task of its
  own (fastpath.py says why, and has the faster way the socket also takes);
  every other message runs in a task of its own, so answers come back as
  they are ready.
- A handler's failure is `rpc.answer`'s to turn into an error response; one
  that escapes it anyway is a bug, logged and answered -32603, and the
  client goes on.
"""

from __future__ import annotations

import asyncio
from collections.abc import Mapping
from typing import Any, Protocol

from hostd.api import rpc


class Sender(Protocol):
    """Where answers go: the client (client.Client, web.WebClient)."""

    log: Any

    def send_line(self, line: bytes) -> bool: ...


class Intake:
    """One client's requests under way, in its connection's task group."""

    def __init__(
        self,
        methods: Mapping[str, rpc.Method],
        client: Sender,
        tg: asyncio.TaskGroup,
        *,
        max_inflight: int,
    ) -> None:
        self._methods = methods
        self._client = client
        self._tg = tg
        self._max_inflight = max_inflight
        self._slots = asyncio.Semaphore(max_inflight)
        self.pending: set[asyncio.Task[None]] = set()  # requests under way or waiting to start

    async def take(self, message: bytes) -> None:
        """Run one message (a line, a frame), or answer why it cannot run."""
        incoming = rpc.decode(message, max_batch=self._max_inflight)
        if incoming.reply is not None:  # not JSON, or a batch that cannot run: nothing runs
            self._client.send_line(incoming.reply)
            return
        for _ in range(incoming.requests):  # the reader is the only taker: no deadlock
            await self._slots.acquire()
        if not self.pending and rpc.is_immediate(incoming, self._methods):
            await self._answer(incoming)  # a realtime byte: no task, no wait
            return
        task = self._tg.create_task(self._answer(incoming))
        self.pending.add(task)
        task.add_done_callback(self.pending.discard)

    async def drain(self) -> None:
        """Until every request taken has been answered."""
        if self.pending:
            await asyncio.wait(self.pending)

    async def _answer(self, incoming: rpc.Incoming) -> None:
        """Answer one message; its requests' slots are given back once all of them are done."""
        try:
            response = await rpc.answer(incoming, self._methods, self._client)
        except Exception:
            # answer() answers everything itself; reaching here is a bug in rpc.py.
            self._client.log.exception("dispatch failed")
            response = rpc.encode_error(rpc.INTERNAL_ERROR, "internal error")
        finally:
            for _ in range(incoming.requests):
                self._slots.release()
        if response is not None:
            self._client.send_line(response)
