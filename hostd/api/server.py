"""The control API's Unix socket: newline-framed JSON-RPC, one task tree per client.

This file only moves lines between sockets and `rpc`; what a line means is
`rpc.py`'s business, what a method does is the API layer's, where the socket
file may live and how it is born is `socketfile.py`'s, how bytes become
lines is `lines.py`'s, which requests skip the queue (a lone realtime
request, such as machine.feedhold) is `fastpath.py`'s, and how a client's
answers and notifications are queued and written is `client.py`'s.

Per client (a `client.Client`):

- One connection task owns everything the client causes: a reader loop, a
  writer task, and one task per request line (requests are handled
  concurrently, so a slow one never holds up the next; answers go out as
  they complete).
- At most `max_inflight` requests run at once, counting each request of a
  batch: a line of n requests waits until n are free, and meanwhile the
  reader stops reading and the socket pushes back on the client. A batch of
  more than `max_inflight` requests could never fit: it is one -32600 and
  none of it runs. So at most one parsed line per client waits on the host.
- Everything sent to the client goes out in the order it was sent, within
  a bounded queue and `write_timeout` (client.py): one that stops reading
  is dropped, and never slows the daemon or anyone else.
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
allowed peer past the cap is told so in one line (error `rpc.SERVER_FULL`, id
null) and closed; nothing it sent is run. At most `max_clients` more
connections may be in admission or being turned away at once; past that a
new connection is closed at once, unread.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import os
from collections.abc import Mapping
from functools import partial
from types import TracebackType
from typing import Final, Self, cast

import structlog

from hostd.api import fastpath, rpc, socketfile
from hostd.api.client import QUEUE_SIZE, WRITE_TIMEOUT, Client, End, flush_staged
from hostd.api.intake import Intake
from hostd.api.lines import LineReader, LineTimeout, LineTooLong
from hostd.api.peer import AccessPolicy, PeerCred, peer_credentials
from hostd.api.tally import Tally

log = structlog.get_logger(__name__)

MAX_LINE: Final = 1 << 20
MAX_INFLIGHT: Final = 128
MAX_CLIENTS: Final = 128
LINE_TIMEOUT: Final = 10.0
# How long a client turned away (the daemon full) gets to read why before it is dropped.
TURN_AWAY_LINGER: Final = 1.0


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
        # Refusals a local flood of connections repeats: a record a second at most, counted.
        self._dropped = Tally(log, "api connection dropped: too many being admitted")
        self._denied = Tally(log, "api client denied")
        self._full = Tally(log, "api client refused: daemon full")
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
        for tally in (self._dropped, self._denied, self._full):
            tally.flush()
        if self._server is not None:
            self._server.close()
        flush_staged()  # what the clients were told last goes out before they are dropped
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
            self._dropped.warning(max=self._max_clients)
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
            self._denied.warning(pid=peer.pid, uid=peer.uid, gid=peer.gid)
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
            await client.serve(partial(self._read_loop, client, reader))
        finally:
            self._clients.discard(client)

    async def _turn_away(
        self, peer: PeerCred, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        """Tell an allowed peer the daemon is full, then hang up without running anything.

        The answer is followed by EOF and whatever the peer sends meanwhile is
        discarded until it hangs up too (or TURN_AWAY_LINGER passes): closing
        with its request unread would reset the connection under the answer.
        """
        self._full.warning(pid=peer.pid, uid=peer.uid, max_clients=self._max_clients)
        message = f"daemon full: {self._max_clients} clients connected; try again later"
        transport = cast(asyncio.Transport, writer.transport)
        with contextlib.suppress(TimeoutError, OSError):
            async with asyncio.timeout(TURN_AWAY_LINGER):
                writer.write(rpc.encode_error(rpc.SERVER_FULL, message) + b"\n")
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
                client._finish(End.CLOSE)
                return
            if line.strip():
                await intake.take(line)

    def _drop_stalled(self, client: Client) -> None:
        """A line left half-sent for line_timeout: say so, then close (a slowloris, or a bug)."""
        client.log.warning("api client stalled mid-line; closing", line_timeout=self._line_timeout)
        message = f"request line not finished within {self._line_timeout:g} s"
        client.send_line(rpc.encode_error(rpc.INVALID_REQUEST, message))
        client._finish(End.CLOSE, f"half a line for over {self._line_timeout:g} s")

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
        client._finish(End.HALF_CLOSE)
        with contextlib.suppress(TimeoutError, OSError):
            async with asyncio.timeout(self._write_timeout):
                while not client.closed and await reader.read(1 << 16):
                    pass
        client.close("request line too long")
