"""The dashboard's HTTP server (`[web]`, docs/web.md): the page, its WebSocket, uploads.

aiohttp serves it: one maintained asyncio library with HTTP, WebSockets and
streamed request bodies, so nothing here parses HTTP or frames WebSockets.

One API. The WebSocket at `/api` carries the same JSON-RPC 2.0 as the Unix
socket, one message a WebSocket text frame, answered by the same method
table through `rpc.answer`. Its peer is a `WebClient`, a `client.Client`
with the WebSocket for a stream, so subscriptions, the bounded outbound
queue (full: the client is dropped) and the disconnect hooks are the Unix
socket's own. `POST /files/<name>` streams a request body into the jobs
directory through the same staging, name rules and quota as `file.upload`.

Security (a browser is not a Unix socket):

- Every request but the login page and its two assets needs a token
  (`hostd token create`, tokens.py): `Authorization: Bearer <token>`, or the
  `hostd_session` cookie that `POST /login` sets (HttpOnly, SameSite=Strict),
  which holds a server-side session id, never the token.
- Revoking a token ends its sessions and closes its WebSockets: the token
  file is looked at every REVOKE_POLL seconds.
- `POST /login` is rate-limited per client address (`login_attempts` a minute);
  the client address is the peer's, or what a `trusted_proxies` proxy says.
- Connections are capped in all and per client address, and a connection
  must send its request's headers within `header_timeout`; an idle one is
  closed after `idle_timeout`. So the web server can never take the
  descriptors the Unix socket, the serial ports and SQLite need.
- The WebSocket handshake, the login and uploads refuse an `Origin` other
  than the served host itself (cross-site WebSocket hijacking, login CSRF).
- Every response carries a Content-Security-Policy that allows scripts,
  styles, images and connections from this origin only: no inline script,
  nothing from the internet, no framing.
- `[web] control = false`: only the methods that read are served; the rest
  answer -32601 naming the setting, and uploads are refused (403).
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import itertools
import json
import time
from collections.abc import Awaitable, Callable, Mapping
from importlib import resources
from typing import Any, Final, NoReturn, cast

import structlog
from aiohttp import WSMsgType, web
from aiohttp.web_protocol import RequestHandler

from hostd.api import rpc
from hostd.api.client import QUEUE_SIZE, WRITE_TIMEOUT, Client
from hostd.api.files import FileNameError, JobsDir, NoSuchFileError, check_name
from hostd.api.intake import Intake
from hostd.api.peer import PeerCred
from hostd.api.server import MAX_INFLIGHT, MAX_LINE
from hostd.api.tokens import Sessions, TokenStore
from hostd.api.uploads import NoSuchUpload, StorageError
from hostd.api.webconfig import WebConfig

log = structlog.get_logger(__name__)

COOKIE: Final = "hostd_session"
CHUNK: Final = 1 << 20  # an upload's body goes to staging a MiB at a time
LOGIN_WINDOW: Final = 60.0
# How often the token file is looked at for revocations (a stat; read only when it changed).
REVOKE_POLL: Final = 0.25
# At most one log line a second about connections refused, with how many.
REFUSAL_LOG_INTERVAL: Final = 1.0
CSP: Final = (
    "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
    "connect-src 'self'; form-action 'self'; base-uri 'none'; frame-ancestors 'none'"
)
HEADERS: Final = {
    "Content-Security-Policy": CSP,
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}
# What a watch-only dashboard may call: reads, and its own subscriptions.
WATCH_METHODS: Final = frozenset(
    {
        "rpc.discover",
        "daemon.info",
        "machine.list",
        "machine.status",
        "settings.get",
        "file.list",
        "file.analyze",
        "job.get",
        "job.list",
        "fault.list",
        "macro.list",
        "subscribe",
        "unsubscribe",
    }
)
STATIC: Final = resources.files("hostd.web") / "static"
ASSETS: Final = {
    "app.js": "text/javascript",
    "login.js": "text/javascript",
    "style.css": "text/css",
    "icon.svg": "image/svg+xml",
}
PUBLIC: Final = frozenset({"/login", "/static/login.js", "/static/style.css", "/static/icon.svg"})
WEB_PEER: Final = PeerCred(pid=0, uid=-1, gid=-1)  # no kernel credentials over TCP
IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network
TOKEN_ID: Final = web.RequestKey("token_id", str)  # the token a request came in with


def watch_only(methods: Mapping[str, rpc.Method]) -> dict[str, rpc.Method]:
    """The table with every method outside WATCH_METHODS answering -32601."""
    return {
        name: method if name in WATCH_METHODS else rpc.Method(_refusal(name), method.params_model)
        for name, method in methods.items()
    }


def _refusal(name: str) -> Callable[..., Awaitable[NoReturn]]:
    async def refused(*_: Any) -> NoReturn:
        message = f"{name} is not available: the web API is watch only ([web] control = false)"
        raise rpc.RpcError(rpc.METHOD_NOT_FOUND, message)

    return refused


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


class LoginLimiter:
    """At most `attempts` logins per address per LOGIN_WINDOW seconds, successful or not."""

    def __init__(self, attempts: int, clock: Callable[[], float] = time.monotonic) -> None:
        self._attempts = attempts
        self._clock = clock
        self._seen: dict[str, list[float]] = {}

    def allow(self, address: str) -> float | None:
        """None when this attempt may go on; else the seconds until one may."""
        now = self._clock()
        recent = [t for t in self._seen.get(address, []) if now - t < LOGIN_WINDOW]
        if len(recent) >= self._attempts:
            self._seen[address] = recent
            return LOGIN_WINDOW - (now - recent[0])
        recent.append(now)
        self._seen[address] = recent
        # Forget quiet addresses, so the table cannot grow without bound.
        if len(self._seen) > 10_000:
            self._seen = {a: ts for a, ts in self._seen.items() if now - ts[-1] < LOGIN_WINDOW}
        return None


class ConnectionGuard:
    """Counts the server's connections: in all, and per client address.

    Asked by each new connection before aiohttp sees a byte of it; one past a
    cap is closed at once (its descriptor freed), and a line is logged at most
    once a second with how many were refused.
    """

    def __init__(
        self,
        total: int,
        per_address: int,
        trusted: list[IPNetwork],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.total = total
        self.per_address = per_address
        self._trusted = trusted
        self._clock = clock
        self._count: dict[str, int] = {}
        self.open = 0
        self.refused = 0
        self._unlogged = 0
        self._logged_at = -1e18

    def admit(self, address: str) -> bool:
        over = None
        if self.open >= self.total:
            over = f"{self.total} connections open ([web] max_connections)"
        elif self._count.get(address, 0) >= self.per_address and not _in_networks(
            address, self._trusted
        ):
            over = f"{self.per_address} from {address} ([web] max_connections_per_address)"
        if over is not None:
            self.refused += 1
            self._unlogged += 1
            now = self._clock()
            if now - self._logged_at >= REFUSAL_LOG_INTERVAL:
                log.warning("web connections refused", refused=self._unlogged, over=over)
                self._unlogged, self._logged_at = 0, now
            return False
        self.open += 1
        self._count[address] = self._count.get(address, 0) + 1
        return True

    def release(self, address: str) -> None:
        self.open -= 1
        left = self._count.get(address, 1) - 1
        if left > 0:
            self._count[address] = left
        else:
            self._count.pop(address, None)


class _Handler(RequestHandler):
    """aiohttp's connection, admitted by the guard, and given `header_timeout` for its
    first request's headers (later ones: aiohttp's keep-alive timeout, our `idle_timeout`)."""

    def __init__(
        self, guard: ConnectionGuard, header_timeout: float, *args: Any, **kwargs: Any
    ) -> None:
        super().__init__(*args, **kwargs)
        self._guard = guard
        self._header_timeout = header_timeout
        self._address: str | None = None
        self._header_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        peer = transport.get_extra_info("peername")
        address = str(peer[0]) if isinstance(peer, tuple) and peer else "?"
        if not self._guard.admit(address):
            cast(asyncio.Transport, transport).abort()
            return
        self._address = address
        super().connection_made(transport)
        loop = asyncio.get_running_loop()
        self._header_timer = loop.call_later(self._header_timeout, self._headers_late)

    def _headers_late(self) -> None:
        self._header_timer = None
        log.warning(
            "web connection closed: no request headers in time",
            address=self._address,
            header_timeout=self._header_timeout,
        )
        if self.transport is not None:
            self.transport.abort()

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if self._header_timer is not None and self._request_count:
            self._header_timer.cancel()
            self._header_timer = None

    def connection_lost(self, exc: BaseException | None) -> None:
        if self._address is None:
            return  # never admitted: aiohttp never saw it
        self._guard.release(self._address)
        self._address = None
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None
        super().connection_lost(exc)


class _Server(web.Server):
    """aiohttp's protocol factory, making `_Handler`s."""

    def __init__(self, base: web.Server, guard: ConnectionGuard, header_timeout: float) -> None:
        super().__init__(
            base.request_handler,
            request_factory=base.request_factory,
            handler_cancellation=base.handler_cancellation,
            loop=base._loop,
            **base._kwargs,
        )
        self._guard = guard
        self._header_timeout = header_timeout

    def __call__(self) -> RequestHandler:
        return _Handler(self._guard, self._header_timeout, self, loop=self._loop, **self._kwargs)


class _Runner(web.AppRunner):
    def __init__(
        self, app: web.Application, guard: ConnectionGuard, header_timeout: float, **kw: Any
    ) -> None:
        super().__init__(app, **kw)
        self._guard = guard
        self._header_timeout = header_timeout

    async def _make_server(self) -> web.Server:
        return _Server(await super()._make_server(), self._guard, self._header_timeout)


def _in_networks(address: str, networks: list[IPNetwork]) -> bool:
    try:
        ip = ipaddress.ip_address(address)
    except ValueError:
        return False
    return any(ip in net for net in networks)


class WebServer:
    """Serves the dashboard on `config.listen` until `close()`."""

    def __init__(
        self,
        methods: Mapping[str, rpc.Method],
        jobs: JobsDir,
        tokens: TokenStore,
        config: WebConfig,
        *,
        max_clients: int = 128,
        max_connections: int | None = None,
        queue_size: int = QUEUE_SIZE,
        write_timeout: float = WRITE_TIMEOUT,
        max_inflight: int = MAX_INFLIGHT,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """`max_connections`: the total cap when the daemon's descriptors make it lower
        than `config.max_connections` (service.py works it out)."""
        self._methods = methods if config.control else watch_only(methods)
        self._jobs = jobs
        self._tokens = tokens
        self._sessions = Sessions(config.session_expiry, clock)
        self._config = config
        self._trusted: list[IPNetwork] = list(config.trusted_proxies)
        total = min(config.max_connections, max_connections or config.max_connections)
        self.guard = ConnectionGuard(total, config.max_connections_per_address, self._trusted)
        self._max_clients = max_clients
        self._queue_size = queue_size
        self._write_timeout = write_timeout
        self._max_inflight = max_inflight
        self._limiter = LoginLimiter(config.login_attempts, clock)
        self._hosts = {"localhost", config.host.strip("[]").lower(), *map(str.lower, config.hosts)}
        self._ids = itertools.count(1)
        self._clients: set[WebClient] = set()
        self._runner: web.AppRunner | None = None
        self._watcher: asyncio.Task[None] | None = None
        self.port: int | None = None

    @property
    def clients(self) -> list[WebClient]:
        return [c for c in self._clients if not c.closed]

    def app(self) -> web.Application:
        app = web.Application(middlewares=[self._authenticate], client_max_size=MAX_LINE)
        app.on_response_prepare.append(_security_headers)
        app.router.add_get("/", self._index)
        app.router.add_get("/login", self._login_page)
        app.router.add_post("/login", self._login)
        app.router.add_post("/logout", self._logout)
        app.router.add_get("/static/{name}", self._asset)
        app.router.add_get("/api", self._api)
        app.router.add_post("/files/{name}", self._upload)
        app.router.add_get("/files/{name}", self._download)
        app.router.add_get("/session", self._session)
        return app

    async def start(self) -> None:
        runner = _Runner(
            self.app(),
            self.guard,
            self._config.header_timeout,
            access_log=None,
            handle_signals=False,
            keepalive_timeout=self._config.idle_timeout,
        )
        await runner.setup()
        site = web.TCPSite(runner, self._config.host, self._config.port)
        try:
            await site.start()
        except BaseException:
            await runner.cleanup()
            raise
        self._runner = runner
        self.port = runner.addresses[0][1]
        self._watcher = asyncio.create_task(self._watch_tokens(), name="web-tokens")
        log.info(
            "web listening",
            host=self._config.host,
            port=self.port,
            max_connections=self.guard.total,
            per_address=self.guard.per_address,
        )

    async def close(self) -> None:
        if self._watcher is not None:
            self._watcher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._watcher
            self._watcher = None
        for client in list(self._clients):
            client.close("server closing")
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
            log.info("web closed")

    # --- security -----------------------------------------------------------

    async def _watch_tokens(self) -> None:
        """A revoked token's sessions end and its WebSockets close, within REVOKE_POLL."""
        while True:
            await asyncio.sleep(REVOKE_POLL)
            try:
                ids = await asyncio.to_thread(self._tokens.ids)
            except (OSError, ValueError, TypeError, KeyError) as exc:
                log.error("web token file unreadable; sessions kept", error=str(exc))
                continue
            self.revoked(ids)

    def revoked(self, ids: set[str]) -> None:
        """Only tokens in `ids` are on file: end the sessions and sockets of the others."""
        ended = self._sessions.keep_only(ids)
        closed = 0
        for client in list(self._clients):
            if client.token_id not in ids and not client.closed:
                client.close("token revoked")
                closed += 1
        if ended or closed:
            log.info("web token revoked: sessions ended", sessions=ended, websockets=closed)

    def client_address(self, request: web.Request) -> str:
        """Who the client is: the peer, or, when the peer is a trusted proxy, the last
        address in X-Forwarded-For that is not one (the proxies append, right to left)."""
        address = request.remote or "?"
        if not self._trusted or not _in_networks(address, self._trusted):
            return address
        hops = [
            h.strip() for h in ",".join(request.headers.getall("X-Forwarded-For", [])).split(",")
        ]
        for hop in reversed([h for h in hops if h]):
            try:
                ipaddress.ip_address(hop)
            except ValueError:
                break  # garbage from further out: believe nothing past it
            address = hop
            if not _in_networks(hop, self._trusted):
                break
        return address

    def _scheme(self, request: web.Request) -> str:
        """http, or what a trusted proxy says the browser used (X-Forwarded-Proto)."""
        if self._trusted and _in_networks(request.remote or "", self._trusted):
            said = request.headers.get("X-Forwarded-Proto", "").split(",")[-1].strip().lower()
            if said in ("http", "https"):
                return said
        return request.scheme

    def _known_host(self, host: str) -> bool:
        """The Host a request names is ours: an address, localhost, `listen`'s, or a [web] host.

        A page on a name the attacker controls, made to resolve to this machine
        (DNS rebinding), names that name: it is refused before anything else.
        """
        name = host.rsplit(":", 1)[0] if not host.endswith("]") else host
        name = name.strip("[]").lower()
        if name in self._hosts:
            return True
        try:
            ipaddress.ip_address(name)
        except ValueError:
            return False
        return True

    def _token_id(self, request: web.Request) -> str | None:
        """The id of the token this request comes with (a bearer token or a session)."""
        header = request.headers.get("Authorization", "")
        scheme, _, value = header.partition(" ")
        if scheme.lower() == "bearer" and value.strip():
            return self._tokens.identify(value.strip())
        token_id = self._sessions.token_id(request.cookies.get(COOKIE))
        if token_id is None or token_id not in self._tokens.ids():
            return None  # revoked since: not even until the next poll
        return token_id

    @web.middleware
    async def _authenticate(
        self, request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
    ) -> web.StreamResponse:
        if not self._known_host(request.host):
            log.warning("web request for an unknown host refused", host=request.host)
            return _error(421, f"this dashboard does not answer to {request.host!r} ([web] hosts)")
        if request.path in PUBLIC:
            return await handler(request)
        token_id = self._token_id(request)
        if token_id is not None:
            request[TOKEN_ID] = token_id
            return await handler(request)
        if request.method == "GET" and request.path == "/":
            raise web.HTTPFound("/login")
        return _error(401, "a token is required: hostd token create (docs/web.md)")

    def _foreign_origin(self, request: web.Request) -> bool:
        """An Origin header naming another site than the one serving this request."""
        origin = request.headers.get("Origin")
        if origin is None:
            return False  # not a browser: browsers send Origin on WebSockets and POSTs
        return origin != f"{self._scheme(request)}://{request.host}"

    # --- pages ----------------------------------------------------------------

    async def _index(self, request: web.Request) -> web.StreamResponse:
        return _page("index.html")

    async def _login_page(self, request: web.Request) -> web.StreamResponse:
        return _page("login.html")

    async def _asset(self, request: web.Request) -> web.StreamResponse:
        name = request.match_info["name"]
        kind = ASSETS.get(name)
        if kind is None:
            raise web.HTTPNotFound()
        return web.Response(body=(STATIC / name).read_bytes(), content_type=kind)

    async def _session(self, request: web.Request) -> web.StreamResponse:
        """What the page needs to know before it connects: may it control?"""
        return web.json_response({"control": self._config.control})

    async def _login(self, request: web.Request) -> web.StreamResponse:
        if self._foreign_origin(request):
            return _error(403, "login from another site refused")
        address = self.client_address(request)
        wait = self._limiter.allow(address)
        if wait is not None:
            log.warning("web login rate-limited", address=address)
            response = _error(429, "too many login attempts; try again later")
            response.headers["Retry-After"] = str(max(1, round(wait)))
            return response
        try:
            body = await request.json()
            token = body["token"] if isinstance(body, dict) else None
        except (ValueError, KeyError):
            token = None
        token_id = self._tokens.identify(token) if isinstance(token, str) else None
        if token_id is None:
            log.warning("web login refused", address=address)
            return _error(401, "not a valid token")
        log.info("web login", address=address, token=token_id)
        response = web.json_response({"control": self._config.control})
        session = self._sessions.create(token_id)
        secure = self._scheme(request) == "https"
        response.set_cookie(
            COOKIE, session, httponly=True, samesite="Strict", path="/", secure=secure
        )
        return response

    async def _logout(self, request: web.Request) -> web.StreamResponse:
        self._sessions.end(request.cookies.get(COOKIE))
        response = web.json_response({})
        response.del_cookie(COOKIE, path="/")
        return response

    # --- files --------------------------------------------------------------

    async def _download(self, request: web.Request) -> web.StreamResponse:
        """A program's text, for the page's preview (the daemon's own jobs directory only)."""
        try:
            path = await asyncio.to_thread(self._jobs.resolve, request.match_info["name"])
        except FileNameError as exc:
            return _error(400, str(exc))
        except NoSuchFileError as exc:
            return _error(404, str(exc))
        return web.FileResponse(path, headers={"Content-Type": "text/plain; charset=utf-8"})

    async def _upload(self, request: web.Request) -> web.StreamResponse:
        """The body, streamed into staging a chunk at a time, published when it ends."""
        if self._foreign_origin(request):
            return _error(403, "upload from another site refused")
        if not self._config.control:
            return _error(403, "uploads are off: the web API is watch only ([web] control = false)")
        try:
            name = check_name(request.match_info["name"])
        except FileNameError as exc:
            return _error(400, str(exc))
        upload: str | None = None
        offset = 0
        finished = False
        try:
            while True:
                try:
                    async with asyncio.timeout(self._config.idle_timeout):
                        chunk = await request.content.read(CHUNK)
                except TimeoutError:
                    log.warning("web upload stalled", file=name, received=offset)
                    return _error(408, f"no data for {self._config.idle_timeout:g} s")
                if not chunk:
                    break
                done = await asyncio.to_thread(
                    self._jobs.upload, name, chunk, final=False, upload_id=upload, offset=offset
                )
                upload, offset = done.upload, offset + len(chunk)
            done = await asyncio.to_thread(
                self._jobs.upload, name, b"", final=True, upload_id=upload, offset=offset
            )
            finished = True
        except StorageError as exc:
            log.warning("web upload refused", file=name, reason=exc.reason, error=exc.message)
            return _error(507, exc.message)
        except NoSuchUpload as exc:  # expired mid-body: only a very slow sender
            return _error(408, str(exc))
        finally:
            if not finished:  # failed or cut off (the peer gone): its staging goes now
                await self._abort_upload(name, upload)
        log.info("web upload", file=name, size=done.size)
        return web.json_response({"name": done.name, "size": done.size})

    async def _abort_upload(self, name: str, upload: str | None) -> None:
        if upload is None:
            return
        try:
            await asyncio.shield(asyncio.to_thread(self._jobs.uploads.abort, upload))
        except OSError as exc:
            log.error("web upload staging not removed", file=name, error=str(exc))
        else:
            log.info("web upload failed; staging removed", file=name)

    # --- the WebSocket --------------------------------------------------------

    async def _api(self, request: web.Request) -> web.StreamResponse:
        if self._foreign_origin(request):
            log.warning("web socket from another site refused", origin=request.headers["Origin"])
            return _error(403, "WebSocket from another site refused")
        if len(self._clients) >= self._max_clients:
            return _error(503, f"daemon full: {self._max_clients} web clients connected")
        ws = web.WebSocketResponse(max_msg_size=MAX_LINE, heartbeat=30.0)
        await ws.prepare(request)
        client = WebClient(
            next(self._ids),
            ws,
            request.transport,
            self.client_address(request),
            queue_size=self._queue_size,
            write_timeout=self._write_timeout,
            token_id=request.get(TOKEN_ID),
        )
        self._clients.add(client)
        client.log.info("web client connected")
        try:
            async with asyncio.TaskGroup() as tg:
                client._writer_task = tg.create_task(client._write_loop())
                await self._read_loop(client, ws, tg)
                # The peer is gone: answers still running are dropped once they finish.
                client.close("connection ended")
        except asyncio.CancelledError:
            client.close("server closing")
            raise
        finally:
            client.close("connection ended")
            client._run_hooks()
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


async def _security_headers(request: web.Request, response: web.StreamResponse) -> None:
    response.headers.update(HEADERS)


def _page(name: str) -> web.Response:
    return web.Response(body=(STATIC / name).read_bytes(), content_type="text/html")


def _error(status: int, message: str) -> web.Response:
    return web.Response(
        status=status,
        body=json.dumps({"error": message}).encode(),
        content_type="application/json",
    )
