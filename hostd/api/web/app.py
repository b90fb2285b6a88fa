"""The dashboard's web server: its routes, the page and its assets, start and close.

What each route does lives with its concern (this package's __init__ lists
them); `WebServer` puts them together: the access checks as middleware, the
security headers on every response, the connection guard in front of aiohttp,
and the token watcher it owns from `start()` to `close()`.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable, Mapping
from importlib import resources
from typing import Final

import structlog
from aiohttp import web

from hostd.api import rpc
from hostd.api.client import QUEUE_SIZE, WRITE_TIMEOUT, flush_staged
from hostd.api.files import JobsDir
from hostd.api.server import MAX_INFLIGHT, MAX_LINE
from hostd.api.tokens import TokenStore
from hostd.api.web.auth import Auth, watch_only
from hostd.api.web.connections import ConnectionGuard, GuardedRunner
from hostd.api.web.files import FileRoutes
from hostd.api.web.responses import security_headers
from hostd.api.web.websocket import WebClient, WebSockets
from hostd.api.webconfig import WebConfig

log = structlog.get_logger(__name__)

STATIC: Final = resources.files("hostd.web") / "static"
ASSETS: Final = {
    "app.js": "text/javascript",
    "login.js": "text/javascript",
    "style.css": "text/css",
    "icon.svg": "image/svg+xml",
}


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
        self._config = config
        self._auth = Auth(tokens, config, clock)
        total = min(config.max_connections, max_connections or config.max_connections)
        self.guard = ConnectionGuard(total, config.max_connections_per_address, self._auth.trusted)
        self._files = FileRoutes(jobs, config, self._auth)
        self._sockets = WebSockets(
            methods if config.control else watch_only(methods),
            self._auth,
            max_clients=max_clients,
            queue_size=queue_size,
            write_timeout=write_timeout,
            max_inflight=max_inflight,
        )
        self._runner: web.AppRunner | None = None
        self._watcher: asyncio.Task[None] | None = None
        self.port: int | None = None

    @property
    def clients(self) -> list[WebClient]:
        return self._sockets.clients

    def app(self) -> web.Application:
        auth = self._auth
        app = web.Application(middlewares=[auth.authenticate], client_max_size=MAX_LINE)
        app.on_response_prepare.append(security_headers)
        app.router.add_get("/", self._index)
        app.router.add_get("/login", self._login_page)
        app.router.add_post("/login", auth.login)
        app.router.add_post("/logout", auth.logout)
        app.router.add_get("/static/{name}", self._asset)
        app.router.add_get("/api", self._sockets.handle)
        app.router.add_post("/files/{name}", self._files.upload)
        app.router.add_get("/files/{name}", self._files.download)
        app.router.add_get("/session", self._session)
        return app

    async def start(self) -> None:
        runner = GuardedRunner(
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
        self._watcher = asyncio.create_task(
            self._auth.watch_tokens(self.revoked), name="web-tokens"
        )
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
        flush_staged()  # what the tabs were told last goes out before they are dropped
        self._sockets.close_all("server closing")
        self._sockets.flush_logs()
        self._auth.flush_logs()
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
            log.info("web closed")

    def revoked(self, ids: set[str]) -> None:
        """Only tokens in `ids` are on file: end the sessions and sockets of the others."""
        ended = self._auth.keep_only(ids)
        closed = self._sockets.close_revoked(ids)
        if ended or closed:
            log.info("web token revoked: sessions ended", sessions=ended, websockets=closed)

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


def _page(name: str) -> web.Response:
    return web.Response(body=(STATIC / name).read_bytes(), content_type="text/html")
