"""The `/api` WebSocket: the socket API's JSON-RPC 2.0, one message a text frame.

Its peer is a `WebClient`, a `client.Client` with the WebSocket for a stream,
so subscriptions, the bounded outbound queue (full: the client is dropped)
and the disconnect hooks are the Unix socket's own, and requests are taken
by the same `intake.py`. The handshake refuses another site's `Origin`
(cross-site WebSocket hijacking); at most `max_clients` are connected.
"""

from __future__ import annotations

import asyncio
import itertools
from collections.abc import Mapping
from functools import partial
from typing import Final

import structlog
from aiohttp import WSMsgType, web

from hostd.api import rpc
from hostd.api.client import QUEUE_SIZE, WRITE_TIMEOUT, Client
from hostd.api.intake import Intake
from hostd.api.peer import PeerCred
from hostd.api.server import MAX_INFLIGHT, MAX_LINE
from hostd.api.tally import Tally
from hostd.api.web.auth import TOKEN_ID, Auth
from hostd.api.web.responses import error

log = structlog.get_logger(__name__)

WEB_PEER: Final = PeerCred(pid=0, uid=-1, gid=-1)  # no kernel credentials over TCP


class WebClient(Client):
    """A browser tab: a `Client` whose messages go out as WebSocket text frames."""

    def __init__(
        self,
        id: int,
        ws: web.WebSocketResponse,
        transport: asyncio.Transport | None,
        remote: str | None,
        *,
        queue_size: int,
        write_timeout: float,
        token_id: str | None = None,
    ) -> None:
        super().__init__(id, WEB_PEER, None, queue_size=queue_size, write_timeout=write_timeout)
        self.log = log.bind(client=id, web=remote, token=token_id)
        self.token_id = token_id  # the token it came in with: revoking it closes this
        self._ws = ws
        self._transport = transport

    def _abort(self) -> None:
        if self._transport is not None:
            self._transport.abort()

    def _direct_transport(self) -> asyncio.WriteTransport | None:
        """The connection's transport while messages may be framed here, in one write.

        Only without permessage-deflate (a compressed frame is aiohttp's to
        make) and before the WebSocket starts closing (no data after a close
        frame). aiohttp writes its own frames (pings, the close) to the same
        transport, each whole, so frames never interleave.
        """
        ws = self._ws
        if ws.compress or ws.closed:
            return None
        return self._transport

    def _write_staged(self, transport: asyncio.WriteTransport, messages: list[bytes]) -> None:
        """One unmasked text frame a message (RFC 6455 5.2), all in one write."""
        transport.write(b"".join(part for m in messages for part in (_text_header(len(m)), m)))

    async def _write_loop(self) -> None:
        """The only writer of the WebSocket: one frame a message, each batch bounded in time.

        Everything queued when the task wakes is sent under one timeout scope:
        with the console topic on, a read of the board's answers queues a
        message a line, and a wake-up and a scope each cost more than the
        frame (docs/performance.md, issue 30).
        """
        queue = self._queue
        try:
            while True:
                item = await queue.get()
                async with asyncio.timeout(self._write_timeout):
                    while True:
                        if not isinstance(item, bytes):
                            return
                        # The bytes every subscriber gets, as encoded once: no decode, no encode.
                        await self._ws.send_frame(item, WSMsgType.TEXT)
                        if queue.empty():
                            break
                        item = queue.get_nowait()
        except TimeoutError:
            self.close(f"write did not drain within {self._write_timeout} s")
        except (OSError, ConnectionError) as e:
            self.close(f"write failed: {e}")


def _text_header(length: int) -> bytes:
    """A server's text frame header: FIN and opcode 1, no mask, then the length (RFC 6455 5.2)."""
    if length < 126:
        return bytes((0x81, length))
    if length < 1 << 16:
        return bytes((0x81, 126)) + length.to_bytes(2, "big")
    return bytes((0x81, 127)) + length.to_bytes(8, "big")


class WebSockets:
    """The `/api` handler and the browser tabs it has connected."""

    def __init__(
        self,
        methods: Mapping[str, rpc.Method],
        auth: Auth,
        *,
        max_clients: int = 128,
        queue_size: int = QUEUE_SIZE,
        write_timeout: float = WRITE_TIMEOUT,
        max_inflight: int = MAX_INFLIGHT,
    ) -> None:
        self._methods = methods
        self._auth = auth
        self._max_clients = max_clients
        self._queue_size = queue_size
        self._write_timeout = write_timeout
        self._max_inflight = max_inflight
        self._ids = itertools.count(1)
        self._foreign = Tally(log, "web socket from another site refused")
        self._clients: set[WebClient] = set()

    @property
    def clients(self) -> list[WebClient]:
        return [c for c in self._clients if not c.closed]

    def flush_logs(self) -> None:
        """Log the refusals still tallied (the server is closing)."""
        self._foreign.flush()

    def close_all(self, reason: str) -> None:
        for client in list(self._clients):
            client.close(reason)

    def close_revoked(self, ids: set[str]) -> int:
        """Close the WebSockets of every token not in `ids`; how many closed."""
        closed = 0
        for client in list(self._clients):
            if client.token_id not in ids and not client.closed:
                client.close("token revoked")
                closed += 1
        return closed

    async def handle(self, request: web.Request) -> web.StreamResponse:
        if self._auth.foreign_origin(request):
            self._foreign.warning(origin=request.headers["Origin"])
            return error(403, "WebSocket from another site refused")
        if len(self._clients) >= self._max_clients:
            return error(503, f"daemon full: {self._max_clients} web clients connected")
        ws = web.WebSocketResponse(max_msg_size=MAX_LINE, heartbeat=30.0)
        await ws.prepare(request)
        client = WebClient(
            next(self._ids),
            ws,
            request.transport,
            self._auth.client_address(request),
            queue_size=self._queue_size,
            write_timeout=self._write_timeout,
            token_id=request.get(TOKEN_ID),
        )
        self._clients.add(client)
        client.log.info("web client connected")
        try:
            await client.serve(partial(self._read_loop, client, ws))
        finally:
            self._clients.discard(client)
        return ws

    async def _read_loop(
        self, client: WebClient, ws: web.WebSocketResponse, tg: asyncio.TaskGroup
    ) -> None:
        """As the Unix socket's (intake.py): one frame a message."""
        intake = Intake(self._methods, client, tg, max_inflight=self._max_inflight)
        async for message in ws:
            if client.closed:
                return
            if message.type != WSMsgType.TEXT:
                client.send_line(rpc.encode_error(rpc.INVALID_REQUEST, "text frames only"))
                continue
            await intake.take(message.data.encode())
        # The peer is gone: answers still running are dropped once they finish.
        client.close("connection ended")
