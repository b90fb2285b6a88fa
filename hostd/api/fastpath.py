"""The realtime fast path: a lone realtime request answered as soon as its bytes are read.

Why: a `!` must reach the board within 1 ms at p99, with a job streaming and
other clients flooding the daemon with queries (docs/performance.md, P2 and
P2f). A request that goes the usual way (`ApiServer._read_loop`) waits for
the client's reader task to be scheduled, a loop pass after its bytes
arrived, and then for a task of its own: under a flood, that loop pass is
most of the millisecond. The fast path skips both waits.

Which methods: those registered with `immediate=True` (`rpc.Methods.register`),
handlers that write a realtime byte and never suspend. `methods.build_methods`
marks machine.feedhold, machine.cycle_start, machine.queue_flush,
machine.job_kill, machine.jog_stop, machine.override and machine.safety_door.
Only a single request takes the fast path (`rpc.is_immediate`): a batch or a
line that is not a request goes the usual way, whatever names it holds.

Two ways, the first one faster:

- In the read callback: the connection's protocol (`Connection`) hands every
  chunk the socket delivers to `FastPath`, which answers it on the spot when
  it is exactly one whole line naming such a method, not over the line
  limit. The handler runs to its end right there (`_run_now`), and the `!` is
  written in the very callback that read the request.
- In the reader task (`intake.Intake`, every transport's): any other lone
  request for such a method that the reader task has read runs in that
  task, not in a task of its own.

Order: a request on the fast path never overtakes an earlier request of the
same client. Either way is taken only while none of the client's earlier
requests is under way or waiting to start (the reader task's `pending` is
empty): a feedhold must not run before the job.resume sent ahead of it. The
callback also needs the client to have nothing unread (no bytes in its
StreamReader, none its LineReader has not yet returned as a line), since
those would be requests sent before this one, and the connection not to be
closed. Anything else reaches the reader task as usual.

The WebSocket transport (web.py) has no read callback of its own to hook:
it has only the reader-task way, under the same rule (the same `Intake`).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Collection, Mapping
from typing import TYPE_CHECKING, Any, cast

from hostd.api import rpc
from hostd.api.lines import LineReader

if TYPE_CHECKING:
    from hostd.api.server import Client


class FastPath:
    """The realtime methods of one server's table, and when a client's request may skip ahead.

    `max_line` and `max_batch` are the server's: a line over the limit is left
    to the reader task, which refuses it.
    """

    def __init__(self, methods: Mapping[str, rpc.Method], *, max_line: int, max_batch: int) -> None:
        self._methods = methods
        self._max_line = max_line
        self._max_batch = max_batch
        # The methods' names as they stand in a request line (quoted), as bytes: a chunk
        # naming none of them is passed on without being decoded.
        self._names = [f'"{name}"'.encode() for name, m in methods.items() if m.immediate]

    def attach(
        self,
        transport: asyncio.BaseTransport,
        client: Client,
        reader: asyncio.StreamReader,
        lines: LineReader,
        pending: Collection[object],
    ) -> None:
        """Answer `client`'s realtime requests in its read callback from now on.

        `pending` is the reader task's set of the client's requests under way;
        the callback takes nothing while it holds any. A transport whose
        protocol is not a `Connection` has no callback to hook: nothing changes.
        """
        connection = transport.get_protocol()
        if isinstance(connection, Connection):
            connection.fast = lambda data: (
                not pending and self._answer_now(client, reader, lines, data)
            )

    def _answer_now(
        self, client: Client, reader: asyncio.StreamReader, lines: LineReader, data: bytes
    ) -> bool:
        """A realtime request answered as its bytes arrive, not a loop pass later; or False.

        Only a chunk that is one whole line naming a realtime method, from a
        client with nothing else unread nor under way (so nothing it sent
        before is overtaken): the `!` of a client beside a query flood is
        written in the very callback that read it.
        """
        if (
            client.closed
            or not data.endswith(b"\n")
            or data.count(b"\n") != 1
            or len(data) > self._max_line
            or not any(name in data for name in self._names)
            or lines.pending
            or _unread(reader)
        ):
            return False
        incoming = rpc.decode(data[:-1], max_batch=self._max_batch)
        if not rpc.is_immediate(incoming, self._methods):
            return False
        response = _run_now(rpc.answer(incoming, self._methods, client))
        if response is not None:
            client.send_line(response)
        return True


class Connection(asyncio.StreamReaderProtocol):
    """A client's connection: a stream, and a fast path for realtime requests (`fast`).

    `fast` is offered every chunk read before the stream is; when it returns
    True it has answered the chunk and the stream never sees it.
    """

    def __init__(
        self,
        reader: asyncio.StreamReader,
        connected: Callable[[asyncio.StreamReader, asyncio.StreamWriter], Any],
    ) -> None:
        super().__init__(reader, connected)
        self.fast: Callable[[bytes], bool] | None = None

    def data_received(self, data: bytes) -> None:
        fast = self.fast
        if fast is None or not fast(data):
            super().data_received(data)


def _unread(reader: asyncio.StreamReader) -> bool:
    """Bytes the reader holds that its task has not taken yet (asyncio keeps them in _buffer)."""
    return bool(getattr(reader, "_buffer", b"x"))


def _run_now(coroutine: Any) -> bytes | None:
    """Run a coroutine that never suspends (an immediate method's answer) to its end, here."""
    try:
        coroutine.send(None)
    except StopIteration as done:
        return cast(bytes | None, done.value)
    coroutine.close()
    raise RuntimeError("an immediate method suspended")
