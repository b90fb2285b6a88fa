"""An API client's connection, whichever transport: its outbound queue and how it is written.

A `Client` is also the `context` handlers can ask for with `current_client()`.
The Unix socket (server.py) makes one per admitted peer, the web API's
WebSocket (web/websocket.py) one per browser tab; both read requests through
`intake.py` and answer through the client.

Everything sent to the client (answers and notifications) goes out in the
order it was sent, one of two ways. While the socket keeps up (nothing
queued, nothing left in the transport's buffer), a message is staged and
written by one callback for every client (`_Flusher`): a status report
for 50 subscribers is 50 list appends and 50 syscalls, not 50 writer-task
wake-ups, timeout scopes and drains (docs/performance.md, issue 30). An
answer (`send_line`) is written at the end of the loop pass it was made in,
with whatever was staged before it. A topic's notification (`send_notice`)
waits up to `NOTICE_DELAY` for the client's next message, so that what a
hold, a status report and a job's progress tell within it reaches each
subscriber in one write and one wake-up of the daemon, not one each
(docs/performance-log.md, "Notifications written together"). Once
the socket lags (its buffer holds bytes), messages go to one bounded
queue emptied by the writer task, which drains each batch within
`write_timeout`. A full queue, or a write that cannot drain within
`write_timeout`, disconnects the client: one that stops reading must never
slow the daemon or anyone else.
"""

from __future__ import annotations

import asyncio
import enum
import weakref
from collections.abc import Awaitable, Callable
from typing import Any, Final

import structlog

from hostd.api import rpc
from hostd.api.peer import PeerCred

log = structlog.get_logger(__name__)

QUEUE_SIZE: Final = 1000
WRITE_TIMEOUT: Final = 10.0
# How long a staged notification waits for others to the same client: about one frame
# of a 50 Hz display, and a twelfth of the `job` topic's 250 ms. Nobody sees it.
NOTICE_DELAY: Final = 0.02


class End(enum.Enum):
    """Queued after the last message: how the writer ends the connection once it is sent."""

    HALF_CLOSE = "half-close"  # send EOF, keep reading (so unread input does not reset us)
    CLOSE = "close"


class _Flusher:
    """Writes every client's staged messages: one callback for all, at two speeds.

    `soon`: at the end of this loop pass (a client has an answer staged).
    `later`: NOTICE_DELAY after the first notification staged (the client has only
    notifications staged). A client is on each list at most once (`_soon`, `_later`);
    one on both is written by whichever runs first, the other finding nothing.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._soon: list[Client] = []
        self._later: list[Client] = []

    def add_soon(self, client: Client) -> None:
        if not self._soon:
            self._loop.call_soon(self._run_soon)
        client._soon = True
        self._soon.append(client)

    def add_later(self, client: Client) -> None:
        if not self._later:
            self._loop.call_later(NOTICE_DELAY, self._run_later)
        client._later = True
        self._later.append(client)

    def _run_soon(self) -> None:
        clients, self._soon = self._soon, []
        for client in clients:
            client._soon = False
        self._flush(clients)

    def _run_later(self) -> None:
        clients, self._later = self._later, []
        for client in clients:
            client._later = False
        self._flush(clients)

    def flush_now(self) -> None:
        """Both lists at once (the server closing): nothing staged is left behind."""
        self._run_soon()
        self._run_later()

    @staticmethod
    def _flush(clients: list[Client]) -> None:
        for client in clients:
            try:
                client._flush()
            except Exception as exc:  # one client's failure is not the others'
                client.log.exception("api client write failed")
                client.close(f"write failed: {exc!r}")


_FLUSHERS: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, _Flusher] = (
    weakref.WeakKeyDictionary()
)


def flush_staged() -> None:
    """Write what every client of this loop has staged, now: before a server drops its
    clients, so that what they were told last (a job interrupted by the daemon's stop)
    is not lost with the wait of NOTICE_DELAY."""
    flusher = _FLUSHERS.get(asyncio.get_running_loop())
    if flusher is not None:
        flusher.flush_now()


def _flusher() -> _Flusher:
    loop = asyncio.get_running_loop()
    flusher = _FLUSHERS.get(loop)
    if flusher is None:
        flusher = _FLUSHERS[loop] = _Flusher(loop)
    return flusher


class Client:
    """One connected peer: its credentials, its outbound queue, its disconnect hooks.

    `on_disconnect` callables (no arguments) run once each, from the event
    loop, soon after the connection is dropped: never inside the call that
    dropped it (e.g. a `notify` made from the machine's event fan-out, which
    the hook may then modify). A hook appended by one of this client's own
    requests runs even if the client left while the request ran (hooks run
    again once its last request is done); one appended from elsewhere after
    `closed` became true does not.

    Another transport (the web API's WebSocket, hostd/api/web/websocket.py) passes no
    stream `writer` and overrides `_abort` and `_write_loop`.
    """

    def __init__(
        self,
        id: int,
        peer: PeerCred,
        writer: asyncio.StreamWriter | None,
        *,
        queue_size: int,
        write_timeout: float,
    ) -> None:
        self.id = id
        self.peer = peer
        self.on_disconnect: list[Callable[[], object]] = []
        self.log = log.bind(client=id, pid=peer.pid, uid=peer.uid)
        self._writer = writer
        # Messages without their newline (the writer adds it), or how to end.
        self._queue: asyncio.Queue[bytes | End] = asyncio.Queue(queue_size)
        self._queue_size = queue_size
        self._write_timeout = write_timeout
        self._closed = False
        self._ending = False  # an End is queued: nothing more goes in
        self._end_reason = "client ended the connection"
        self._writer_task: asyncio.Task[None] | None = None
        # Messages to write at the end of this loop pass, while the socket keeps up.
        self._staged: list[bytes] = []
        # Looked up once, not once a message: a notification to 50 subscribers is 50 calls.
        self._transport = writer.transport if writer is not None else None
        self._flusher: _Flusher | None = None  # this loop's, from the first message staged
        self._soon = False  # on the flusher's list for the end of this pass
        self._later = False  # on its list for NOTICE_DELAY from the first notification

    @property
    def pid(self) -> int:
        return self.peer.pid

    @property
    def uid(self) -> int:
        return self.peer.uid

    @property
    def gid(self) -> int:
        return self.peer.gid

    @property
    def closed(self) -> bool:
        return self._closed

    def notify(self, method: str, params: Any = None) -> None:
        """Queue a JSON-RPC notification; never blocks, never raises. Event loop thread only.

        Dropped when the client is gone (or goes now, its queue being full) and
        when the params are not JSON-serialisable (logged). Check `closed` to
        stop producing for a client that left. Notifications queued while a
        request runs go out before that request's answer.
        """
        if self._closed or self._ending:
            return
        try:
            line = rpc.encode_notification(method, params)
        except Exception:
            self.log.exception("notification is not JSON-serialisable", method=method)
            return
        self.send_line(line)

    def send_line(self, line: bytes) -> bool:
        """Queue one already-encoded message (without its newline); False if dropped.

        An answer, or anything that must not wait: written at the end of this
        loop pass, after whatever was staged before it.
        """
        return self._stage(line, True)

    def send_notice(self, line: bytes) -> bool:
        """Queue one already-encoded notification of a topic; False if dropped.

        For fan-out: encode once with `rpc.encode_notification`, send to many. It
        waits up to NOTICE_DELAY for this client's next messages, to go in one
        write with them; an answer staged meanwhile takes it along at once.
        """
        return self._stage(line, False)

    def _stage(self, line: bytes, soon: bool) -> bool:
        if self._closed or self._ending:
            return False
        staged = self._staged
        if staged:
            # The line itself: a notification's one encoding is shared by every subscriber.
            staged.append(line)
            if len(staged) > self._queue_size:
                self.log.warning("api client not reading; disconnected", bound=self._queue_size)
                self.close(f"outbound queue over {self._queue_size} messages")
                return False
        elif self._keeps_up():
            staged.append(line)
        else:
            return self._enqueue(line)
        # Staged: a flush is due, at this pass's end for an answer, else within NOTICE_DELAY
        # (while anything is staged the client is on one list or the other already).
        if soon:
            if not self._soon:
                self._flusher_of_loop().add_soon(self)
        elif not (self._soon or self._later):
            self._flusher_of_loop().add_later(self)
        return True

    def _flusher_of_loop(self) -> _Flusher:
        flusher = self._flusher
        if flusher is None:
            flusher = self._flusher = _flusher()
        return flusher

    def _keeps_up(self) -> bool:
        """Nothing waits for the writer task and the socket holds nothing unsent."""
        transport = self._direct_transport()
        return (
            transport is not None
            and self._queue.empty()
            and not transport.is_closing()
            and transport.get_write_buffer_size() == 0
        )

    def _direct_transport(self) -> asyncio.WriteTransport | None:
        """Where staged messages may be written straight, or None (always through the task)."""
        return self._transport

    def _write_staged(self, transport: asyncio.WriteTransport, messages: list[bytes]) -> None:
        """Messages as this connection frames them, in one write: a newline after each."""
        if len(messages) == 1:  # the usual case: one notification this pass
            transport.write(messages[0] + b"\n")
            return
        messages.append(b"")  # the last message's newline
        transport.write(b"\n".join(messages))

    def _flush(self) -> None:
        """This pass's staged messages: in one write while the socket keeps up, else queued.

        The first message was staged only because the socket kept up (`_stage`),
        and while messages are staged nothing is queued and nothing of ours is
        written: only whether the connection began to close meanwhile is asked
        again (the queue and the write buffer were a third of a notification's
        cost a subscriber, docs/performance.md).
        """
        staged, self._staged = self._staged, []
        if self._closed or not staged:
            return
        transport = self._direct_transport()
        if transport is None or transport.is_closing():
            for line in staged:
                if not self._enqueue(line):
                    return
            return
        try:
            self._write_staged(transport, staged)
        except OSError as e:
            self.close(f"write failed: {e}")

    def _enqueue(self, line: bytes) -> bool:
        try:
            self._queue.put_nowait(line)
        except asyncio.QueueFull:
            self.log.warning("api client not reading; disconnected", bound=self._queue_size)
            self.close(f"outbound queue over {self._queue_size} messages")
            return False
        return True

    async def serve(self, read: Callable[[asyncio.TaskGroup], Awaitable[None]]) -> None:
        """The connection's life, whichever transport: the writer task and `read(tg)` in
        one task group (`read` starts each request as a task of `tg`).

        Returns once the writer and every request have ended; cancelled (the server
        closing), the client is closed first. Either way the disconnect hooks run
        before this returns.
        """
        try:
            async with asyncio.TaskGroup() as tg:
                self._writer_task = tg.create_task(self._write_loop())
                await read(tg)
        except asyncio.CancelledError:
            self.close("server closing")
            raise
        finally:
            self.close("connection ended")
            self._run_hooks()

    def close(self, reason: str = "closed") -> None:
        """Drop the connection now, discarding anything not yet sent. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self.log.info("api client disconnected", reason=reason)
        self._abort()
        if self._writer_task is not None and self._writer_task is not asyncio.current_task():
            self._writer_task.cancel()
        asyncio.get_running_loop().call_soon(self._run_hooks)

    def _abort(self) -> None:
        """Drop the transport at once, unsent data and all."""
        if self._writer is not None:
            self._writer.transport.abort()

    def _finish(self, end: End, reason: str = "client ended the connection") -> None:
        """Let the writer send what is queued, then end the connection as `end` says.

        `reason` is what the disconnect is logged with, once `CLOSE` has closed it.
        """
        if self._closed or self._ending:
            return
        self._end_reason = reason
        staged, self._staged = self._staged, []  # they go first, through the writer task
        for line in staged:
            if not self._enqueue(line):
                return
        try:
            self._queue.put_nowait(end)
        except asyncio.QueueFull:
            self.close(f"outbound queue over {self._queue_size} messages")
            return
        self._ending = True

    def _run_hooks(self) -> None:
        while self.on_disconnect:
            hook = self.on_disconnect.pop(0)
            try:
                hook()
            except Exception:
                self.log.exception("disconnect hook failed")

    async def _write_loop(self) -> None:
        """The only writer of this socket: sends queued messages in batches, one drain each."""
        assert self._writer is not None
        try:
            while True:
                batch: list[bytes] = []
                end: End | None = None
                item = await self._queue.get()
                while True:
                    if isinstance(item, End):
                        end = item
                        break
                    batch.append(item)
                    batch.append(b"\n")
                    if self._queue.empty():
                        break
                    item = self._queue.get_nowait()
                if batch:
                    self._writer.write(b"".join(batch))
                    async with asyncio.timeout(self._write_timeout):
                        await self._writer.drain()
                if end is End.HALF_CLOSE:
                    self._writer.write_eof()
                    return
                if end is End.CLOSE:
                    self._writer.close()
                    async with asyncio.timeout(self._write_timeout):
                        await self._writer.wait_closed()
                    self.close(self._end_reason)
                    return
        except TimeoutError:
            self.close(f"write did not drain within {self._write_timeout} s")
        except OSError as e:
            self.close(f"write failed: {e}")


def current_client() -> Client:
    """The client whose request is being handled (for subscriptions and the like).

    Raises LookupError outside a request handler.
    """
    context = rpc.current_context()
    if not isinstance(context, Client):
        raise LookupError("the RPC context is not an API client")
    return context
