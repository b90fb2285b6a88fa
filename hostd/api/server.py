"""The control API's Unix socket: newline-framed JSON-RPC, one task tree per client.

This file only moves lines between sockets and `rpc`; what a line means is
`rpc.py`'s business, what a method does is the API layer's, where the socket
file may live and how it is born is `socketfile.py`'s, how bytes become
lines is `lines.py`'s, and which requests skip the queue (a lone realtime
request, such as machine.feedhold) is `fastpath.py`'s.

Per client (a `Client`, which is also the `context` handlers can ask for with
`current_client()`):

- One connection task owns everything the client causes: a reader loop, a
  writer task, and one task per request line (requests are handled
  concurrently, so a slow one never holds up the next; answers go out as
  they complete).
- At most `max_inflight` requests run at once, counting each request of a
  batch: a line of n requests waits until n are free, and meanwhile the
  reader stops reading and the socket pushes back on the client. A batch of
  more than `max_inflight` requests could never fit: it is one -32600 and
  none of it runs. So at most one parsed line per client waits on the host.
- Everything sent to the client (answers and notifications) goes out in the
  order it was sent, one of two ways. While the socket keeps up (nothing
  queued, nothing left in the transport's buffer), a message is staged and
  everything staged in a loop pass is written at the pass's end in one
  `send`, by one callback for every client (`_Flusher`): a status report
  for 50 subscribers is 50 list appends and 50 syscalls, not 50 writer-task
  wake-ups, timeout scopes and drains (docs/performance.md, issue 30). Once
  the socket lags (its buffer holds bytes), messages go to one bounded
  queue emptied by the writer task, which drains each batch within
  `write_timeout`. A full queue, or a write that cannot drain within
  `write_timeout`, disconnects the client: one that stops reading must never
  slow the daemon or anyone else.
- When the client goes away, requests it already started run to completion
  (their answers are dropped): cancelling a machine operation half-way because
  a CLI was closed would be worse. Closing the server cancels them.

Lines longer than `max_line` are answered with -32600 and the connection is
closed; so is a line left half-sent for `line_timeout` seconds (a client
quiet between lines stays connected however long). A client that ends its
side (EOF) gets the answers to the requests it sent before the connection is
closed.

Connections: at most `max_clients` admitted clients at once. A connection
counts from its admission until its last request has finished, even when its
peer has already gone (its requests still hold the daemon's resources). An
allowed peer past the cap is told so in one line (error `SERVER_FULL`, id
null) and closed; nothing it sent is run. At most `max_clients` more
connections may be in admission or being turned away at once; past that a
new connection is closed at once, unread.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import itertools
import os
import weakref
from collections.abc import Callable, Mapping
from types import TracebackType
from typing import Any, Final, Self, cast

import structlog

from hostd.api import fastpath, rpc, socketfile
from hostd.api.intake import Intake
from hostd.api.lines import LineReader, LineTimeout, LineTooLong
from hostd.api.peer import AccessPolicy, PeerCred, peer_credentials

log = structlog.get_logger(__name__)

MAX_LINE: Final = 1 << 20
QUEUE_SIZE: Final = 1000
WRITE_TIMEOUT: Final = 10.0
MAX_INFLIGHT: Final = 128
MAX_CLIENTS: Final = 128
LINE_TIMEOUT: Final = 10.0
# How long a client turned away (the daemon full) gets to read why before it is dropped.
TURN_AWAY_LINGER: Final = 1.0
# JSON-RPC leaves -32000 to -32099 to the server: the daemon has max_clients connected.
SERVER_FULL: Final = -32000


class _End(enum.Enum):
    """Queued after the last message: how the writer ends the connection once it is sent."""

    HALF_CLOSE = "half-close"  # send EOF, keep reading (so unread input does not reset us)
    CLOSE = "close"


class _Flusher:
    """Writes every client's staged messages at the end of the loop pass: one callback for all."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._clients: list[Client] = []

    def add(self, client: Client) -> None:
        if not self._clients:
            self._loop.call_soon(self._run)
        self._clients.append(client)

    def _run(self) -> None:
        clients, self._clients = self._clients, []
        for client in clients:
            try:
                client._flush()
            except Exception as exc:  # one client's failure is not the others'
                client.log.exception("api client write failed")
                client.close(f"write failed: {exc!r}")


_FLUSHERS: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, _Flusher] = (
    weakref.WeakKeyDictionary()
)


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

    Another transport (the web API's WebSocket, hostd/api/web.py) passes no
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
        self._queue: asyncio.Queue[bytes | _End] = asyncio.Queue(queue_size)
        self._queue_size = queue_size
        self._write_timeout = write_timeout
        self._closed = False
        self._ending = False  # an _End is queued: nothing more goes in
        self._end_reason = "client ended the connection"
        self._writer_task: asyncio.Task[None] | None = None
        # Messages to write at the end of this loop pass, while the socket keeps up.
        self._staged: list[bytes] = []
        # Looked up once, not once a message: a notification to 50 subscribers is 50 calls.
        self._transport = writer.transport if writer is not None else None
        self._flusher: _Flusher | None = None  # this loop's, from the first message staged

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

        For fan-out: encode once with `rpc.encode_notification`, send to many.
        """
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
            return True
        if self._keeps_up():
            staged.append(line)
            flusher = self._flusher
            if flusher is None:
                flusher = self._flusher = _flusher()
            flusher.add(self)
            return True
        return self._enqueue(line)

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
        """This pass's staged messages: in one write while the socket keeps up, else queued."""
        staged, self._staged = self._staged, []
        if self._closed or not staged:
            return
        if not self._keeps_up():
            for line in staged:
                if not self._enqueue(line):
                    return
            return
        transport = self._direct_transport()
        assert transport is not None
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

    def _finish(self, end: _End, reason: str = "client ended the connection") -> None:
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
                end: _End | None = None
                item = await self._queue.get()
                while True:
                    if isinstance(item, _End):
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
                if end is _End.HALF_CLOSE:
                    self._writer.write_eof()
                    return
                if end is _End.CLOSE:
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


class ApiServer:
    """Serves a method table on a Unix socket until `close()`.

    Usage::

        async with ApiServer(methods, policy=AccessPolicy.default("hostd")) as server:
            await server.start("/run/hostd/hostd.sock")
            ...  # serve until shutdown; leaving the block closes everything
    """

    def __init__(
        self,
        methods: Mapping[str, rpc.Method],
        *,
        policy: AccessPolicy | None = None,
        socket_gid: int | None = None,
        max_line: int = MAX_LINE,
        queue_size: int = QUEUE_SIZE,
        write_timeout: float = WRITE_TIMEOUT,
        max_inflight: int = MAX_INFLIGHT,
        max_clients: int = MAX_CLIENTS,
        line_timeout: float = LINE_TIMEOUT,
    ) -> None:
        """`policy` defaults to root and the daemon's own user; `socket_gid`, when
        given, becomes the socket file's group (the file is then 0660 so that
        the group can connect, the policy must still allow them; else 0600)."""
        self._methods = methods
        self._fast = fastpath.FastPath(methods, max_line=max_line, max_batch=max_inflight)
        self._policy = policy if policy is not None else AccessPolicy.default()
        self._socket_gid = socket_gid
        self._max_line = max_line
        self._queue_size = queue_size
        self._write_timeout = write_timeout
        self._max_inflight = max_inflight
        self._max_clients = max_clients
        self._line_timeout = line_timeout
        self._server: asyncio.Server | None = None
        self._path: str | None = None
        self._inode: tuple[int, int] | None = None
        self._closing = False
        self._ids = itertools.count(1)
        self._clients: set[Client] = set()  # admitted, until their last request is done
        self._unadmitted = 0  # connections being admitted or turned away
        self._connections: set[asyncio.Task[None]] = set()

    @property
    def path(self) -> str | None:
        return self._path

    @property
    def clients(self) -> list[Client]:
        """The clients connected now."""
        return [c for c in self._clients if not c.closed]

    @property
    def admitted(self) -> int:
        """Connections counted against `max_clients`: those connected, and those that
        left with requests still running."""
        return len(self._clients)

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    async def start(self, path: str | os.PathLike[str]) -> None:
        """Listen on `path`. Raises `socketfile.SocketPathError` (one line, for the
        operator) if the path cannot be used: see socketfile.py."""
        if self._server is not None or self._closing:
            raise RuntimeError("ApiServer.start() called twice")
        where = os.fspath(path)
        socketfile.prepare(where)
        bound = socketfile.bind(where, self._socket_gid)
        self._inode = bound.inode
        try:
            loop = asyncio.get_running_loop()
            self._server = await loop.create_unix_server(
                lambda: fastpath.Connection(
                    asyncio.StreamReader(self._max_line, loop), self._accept
                ),
                sock=bound.sock,
            )
        except BaseException:
            bound.sock.close()
            socketfile.unlink_own(where, bound.inode)
            raise
        self._path = where
        log.info(
            "api listening",
            path=where,
            gid=self._socket_gid,
            max_line=self._max_line,
            max_clients=self._max_clients,
        )

    async def close(self) -> None:
        """Stop accepting, drop every client (cancelling their requests), remove the socket file."""
        self._closing = True
        if self._server is not None:
            self._server.close()
        tasks = list(self._connections)
        for task in tasks:
            task.cancel()
        if tasks:
            await asyncio.gather(*tasks, return_exceptions=True)
        if self._server is not None:
            await self._server.wait_closed()
            self._server = None
        if self._path is not None and self._inode is not None:
            socketfile.unlink_own(self._path, self._inode)
            log.info("api closed", path=self._path)
            self._path = None

    # --- per connection -----------------------------------------------------

    def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        transport = cast(asyncio.Transport, writer.transport)
        # Nothing is read from a peer before the policy has let it in.
        transport.pause_reading()
        if self._closing:
            transport.abort()
            return
        if self._unadmitted >= self._max_clients:
            # A flood of connections: do not even ask who they are (a thread each).
            log.warning("api connection dropped: too many being admitted", max=self._max_clients)
            transport.abort()
            return
        self._unadmitted += 1
        task = asyncio.create_task(self._serve(reader, writer))
        self._connections.add(task)
        task.add_done_callback(self._connections.discard)

    async def _admit(self, writer: asyncio.StreamWriter) -> PeerCred | None:
        try:
            peer = peer_credentials(writer.get_extra_info("socket"))
        except OSError as e:
            log.warning("api peer credentials unavailable; closed", error=str(e))
            return None
        # The policy may ask NSS (possibly LDAP): keep the event loop free meanwhile.
        try:
            allowed = await asyncio.to_thread(self._policy.allows, peer)
        except Exception:
            log.exception("api access check failed; closed", pid=peer.pid, uid=peer.uid)
            return None
        if not allowed:
            log.warning("api client denied", pid=peer.pid, uid=peer.uid, gid=peer.gid)
            return None
        return peer

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        transport = cast(asyncio.Transport, writer.transport)
        try:
            try:
                peer = await self._admit(writer)
                if peer is not None and len(self._clients) >= self._max_clients:
                    await self._turn_away(peer, reader, writer)
                    peer = None
            finally:
                self._unadmitted -= 1
        except BaseException:
            transport.abort()
            raise
        if peer is None:
            transport.abort()
            return
        client = Client(
            next(self._ids),
            peer,
            writer,
            queue_size=self._queue_size,
            write_timeout=self._write_timeout,
        )
        self._clients.add(client)
        client.log.info("api client connected", gid=peer.gid)
        transport.resume_reading()
        try:
            async with asyncio.TaskGroup() as tg:
                client._writer_task = tg.create_task(client._write_loop())
                await self._read_loop(client, reader, tg)
        except asyncio.CancelledError:
            client.close("server closing")
            raise
        finally:
            client.close("connection ended")
            client._run_hooks()
            self._clients.discard(client)

    async def _turn_away(
        self, peer: PeerCred, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        """Tell an allowed peer the daemon is full, then hang up without running anything.

        The answer is followed by EOF and whatever the peer sends meanwhile is
        discarded until it hangs up too (or TURN_AWAY_LINGER passes): closing
        with its request unread would reset the connection under the answer.
        """
        log.warning(
            "api client refused: daemon full",
            pid=peer.pid,
            uid=peer.uid,
            max_clients=self._max_clients,
        )
        message = f"daemon full: {self._max_clients} clients connected; try again later"
        transport = cast(asyncio.Transport, writer.transport)
        with contextlib.suppress(TimeoutError, OSError):
            async with asyncio.timeout(TURN_AWAY_LINGER):
                writer.write(rpc.encode_error(SERVER_FULL, message) + b"\n")
                writer.write_eof()
                transport.resume_reading()
                await writer.drain()
                while await reader.read(1 << 16):
                    pass

    async def _read_loop(
        self, client: Client, reader: asyncio.StreamReader, tg: asyncio.TaskGroup
    ) -> None:
        lines = LineReader(reader, max_line=self._max_line, line_timeout=self._line_timeout)
        intake = Intake(self._methods, client, tg, max_inflight=self._max_inflight)
        if client._writer is not None:
            self._fast.attach(client._writer.transport, client, reader, lines, intake.pending)
        while not client.closed:
            try:
                line = await lines.readline()
            except LineTooLong:
                await self._refuse_long_line(client, reader)
                return
            except LineTimeout:
                self._drop_stalled(client)
                return
            except OSError as e:
                client.close(f"read failed: {e}")
                return
            if line is None:
                # EOF: the client is done sending; answer what it asked, then close.
                await intake.drain()
                client._finish(_End.CLOSE)
                return
            if line.strip():
                await intake.take(line)

    def _drop_stalled(self, client: Client) -> None:
        """A line left half-sent for line_timeout: say so, then close (a slowloris, or a bug)."""
        client.log.warning("api client stalled mid-line; closing", line_timeout=self._line_timeout)
        message = f"request line not finished within {self._line_timeout:g} s"
        client.send_line(rpc.encode_error(rpc.INVALID_REQUEST, message))
        client._finish(_End.CLOSE, f"half a line for over {self._line_timeout:g} s")

    async def _refuse_long_line(self, client: Client, reader: asyncio.StreamReader) -> None:
        """Answer -32600, then close without resetting the connection under the answer.

        Closing a Unix socket with unread input makes the peer's next read fail
        with ECONNRESET, possibly before it reads our answer. So: send the answer
        and EOF, discard whatever the client still sends until it closes its end
        (or `write_timeout` passes), then close.
        """
        client.log.warning("api request line too long; closing", max_line=self._max_line)
        message = f"request line over {self._max_line} bytes"
        client.send_line(rpc.encode_error(rpc.INVALID_REQUEST, message))
        client._finish(_End.HALF_CLOSE)
        with contextlib.suppress(TimeoutError, OSError):
            async with asyncio.timeout(self._write_timeout):
                while not client.closed and await reader.read(1 << 16):
                    pass
        client.close("request line too long")
