"""The dashboard's HTTP server (`[web]`, docs/web.md): the page, its WebSocket, uploads.

aiohttp serves it: one maintained asyncio library with HTTP, WebSockets and
streamed request bodies, so nothing here parses HTTP or frames WebSockets.

One API. The WebSocket at `/api` carries the same JSON-RPC 2.0 as the Unix
socket, one message a WebSocket text frame, answered by the same method
table through `rpc.answer`. Its peer is a `WebClient`, a `server.Client`
with the WebSocket for a stream, so subscriptions, the bounded outbound
queue (full: the client is dropped) and the disconnect hooks are the Unix
socket's own. `POST /files/<name>` streams a request body into the jobs
directory through the same staging, name rules and quota as `file.upload`.

Security (a browser is not a Unix socket):

- Every request but the login page and its two assets needs a token
  (`hostd token create`, tokens.py): `Authorization: Bearer <token>`, or the
  `hostd_session` cookie that `POST /login` sets (HttpOnly, SameSite=Strict).
- `POST /login` is rate-limited per client address (`login_attempts` a minute).
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
import ipaddress
import itertools
import json
import time
from collections.abc import Awaitable, Callable, Mapping
from importlib import resources
from typing import Any, Final, NoReturn

import structlog
from aiohttp import WSMsgType, web

from hostd.api import rpc
from hostd.api.files import FileNameError, JobsDir, NoSuchFileError, check_name
from hostd.api.intake import Intake
from hostd.api.peer import PeerCred
from hostd.api.server import MAX_INFLIGHT, MAX_LINE, QUEUE_SIZE, WRITE_TIMEOUT, Client
from hostd.api.tokens import TokenStore
from hostd.api.uploads import NoSuchUpload, StorageError
from hostd.config import WebConfig

log = structlog.get_logger(__name__)

COOKIE: Final = "hostd_session"
CHUNK: Final = 1 << 20  # an upload's body goes to staging a MiB at a time
LOGIN_WINDOW: Final = 60.0
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
    ) -> None:
        super().__init__(id, WEB_PEER, None, queue_size=queue_size, write_timeout=write_timeout)
        self.log = log.bind(client=id, web=remote)
        self._ws = ws
        self._transport = transport

    def _abort(self) -> None:
        if self._transport is not None:
            self._transport.abort()

    async def _write_loop(self) -> None:
        """The only writer of the WebSocket: one frame a message, each send bounded in time."""
        try:
            while True:
                item = await self._queue.get()
                if not isinstance(item, bytes):
                    return
                async with asyncio.timeout(self._write_timeout):
                    await self._ws.send_str(item[:-1].decode())
        except TimeoutError:
            self.close(f"write did not drain within {self._write_timeout} s")
        except (OSError, ConnectionError) as e:
            self.close(f"write failed: {e}")


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
        queue_size: int = QUEUE_SIZE,
        write_timeout: float = WRITE_TIMEOUT,
        max_inflight: int = MAX_INFLIGHT,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._methods = methods if config.control else watch_only(methods)
        self._jobs = jobs
        self._tokens = tokens
        self._config = config
        self._max_clients = max_clients
        self._queue_size = queue_size
        self._write_timeout = write_timeout
        self._max_inflight = max_inflight
        self._limiter = LoginLimiter(config.login_attempts, clock)
        self._hosts = {"localhost", config.host.strip("[]").lower(), *map(str.lower, config.hosts)}
        self._ids = itertools.count(1)
        self._clients: set[WebClient] = set()
        self._runner: web.AppRunner | None = None
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
        runner = web.AppRunner(self.app(), access_log=None, handle_signals=False)
        await runner.setup()
        site = web.TCPSite(runner, self._config.host, self._config.port)
        try:
            await site.start()
        except BaseException:
            await runner.cleanup()
            raise
        self._runner = runner
        self.port = runner.addresses[0][1]
        log.info("web listening", host=self._config.host, port=self.port)

    async def close(self) -> None:
        for client in list(self._clients):
            client.close("server closing")
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
            log.info("web closed")

    # --- security -----------------------------------------------------------

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

    def _token(self, request: web.Request) -> str | None:
        header = request.headers.get("Authorization", "")
        scheme, _, value = header.partition(" ")
        if scheme.lower() == "bearer" and value.strip():
            return value.strip()
        return request.cookies.get(COOKIE)

    @web.middleware
    async def _authenticate(
        self, request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
    ) -> web.StreamResponse:
        if not self._known_host(request.host):
            log.warning("web request for an unknown host refused", host=request.host)
            return _error(421, f"this dashboard does not answer to {request.host!r} ([web] hosts)")
        if request.path in PUBLIC or self._tokens.verify(self._token(request)):
            return await handler(request)
        if request.method == "GET" and request.path == "/":
            raise web.HTTPFound("/login")
        return _error(401, "a token is required: hostd token create (docs/web.md)")

    def _foreign_origin(self, request: web.Request) -> bool:
        """An Origin header naming another site than the one serving this request."""
        origin = request.headers.get("Origin")
        if origin is None:
            return False  # not a browser: browsers send Origin on WebSockets and POSTs
        return origin != f"{request.scheme}://{request.host}"

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
        address = request.remote or "?"
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
        if not isinstance(token, str) or not self._tokens.verify(token):
            log.warning("web login refused", address=address)
            return _error(401, "not a valid token")
        log.info("web login", address=address)
        response = web.json_response({"control": self._config.control})
        response.set_cookie(COOKIE, token, httponly=True, samesite="Strict", path="/")
        return response

    async def _logout(self, request: web.Request) -> web.StreamResponse:
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
        try:
            while True:
                chunk = await request.content.read(CHUNK)
                if not chunk:
                    break
                done = await asyncio.to_thread(
                    self._jobs.upload, name, chunk, final=False, upload_id=upload, offset=offset
                )
                upload, offset = done.upload, offset + len(chunk)
            done = await asyncio.to_thread(
                self._jobs.upload, name, b"", final=True, upload_id=upload, offset=offset
            )
        except StorageError as exc:
            log.warning("web upload refused", file=name, reason=exc.reason, error=exc.message)
            return _error(507, exc.message)
        except NoSuchUpload as exc:  # expired mid-body: only a very slow sender
            return _error(408, str(exc))
        log.info("web upload", file=name, size=done.size)
        return web.json_response({"name": done.name, "size": done.size})

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
            request.remote,
            queue_size=self._queue_size,
            write_timeout=self._write_timeout,
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
