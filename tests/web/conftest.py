"""A whole daemon (a simulated machine) with the web server on a loopback port, and a token;
and Debian's chromium driven by Playwright for the browser tests (it never downloads one).

HOSTD_SCREENSHOTS=DIR keeps the browser tests' screenshots there too (docs/screenshots is
where the README's come from)."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import os
import shutil
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiohttp
import playwright.async_api as playwright
import pytest
import pytest_asyncio

from hostd.api.methods import build_methods
from hostd.api.tokens import TokenStore
from hostd.api.web import WebServer
from hostd.config import WebConfig
from tests.daemon.conftest import Running, running_daemon


@dataclass
class Web:
    hostd: Running
    server: WebServer
    token: str
    session: aiohttp.ClientSession

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server.port}"

    def auth(self, token: str | None = None) -> dict[str, str]:
        return {"Authorization": f"Bearer {token or self.token}"}

    async def ws(self, **kwargs: Any) -> WsRpc:
        kwargs.setdefault("headers", self.auth())
        return WsRpc(await self.session.ws_connect(f"{self.url}/api", **kwargs))


class WsRpc:
    """JSON-RPC over one WebSocket: calls matched by id, notifications queued."""

    def __init__(self, ws: aiohttp.ClientWebSocketResponse) -> None:
        self.ws = ws
        self._ids = itertools.count(1)
        self._waiting: dict[int, asyncio.Future[dict[str, Any]]] = {}
        self.notifications: asyncio.Queue[dict[str, Any]] = asyncio.Queue()
        self.closed = asyncio.Event()
        self._task = asyncio.create_task(self._read())

    async def _read(self) -> None:
        try:
            async for message in self.ws:
                msg = json.loads(message.data)
                if "id" in msg and msg["id"] in self._waiting:
                    self._waiting.pop(msg["id"]).set_result(msg)
                elif "method" in msg:
                    self.notifications.put_nowait(msg)
        finally:
            self.closed.set()

    async def request(self, method: str, **params: Any) -> dict[str, Any]:
        msg_id = next(self._ids)
        future = asyncio.get_running_loop().create_future()
        self._waiting[msg_id] = future
        message: dict[str, Any] = {"jsonrpc": "2.0", "id": msg_id, "method": method}
        if params:
            message["params"] = params
        await self.ws.send_str(json.dumps(message))
        async with asyncio.timeout(15):
            return await future

    async def call(self, method: str, **params: Any) -> Any:
        msg = await self.request(method, **params)
        assert "error" not in msg, msg["error"]
        return msg["result"]

    async def notification(self, predicate: Callable[[dict[str, Any]], bool]) -> dict[str, Any]:
        async with asyncio.timeout(10):
            while True:
                msg = await self.notifications.get()
                if predicate(msg):
                    return msg

    def queued(self) -> list[dict[str, Any]]:
        """The notifications received and not yet taken, taken now, in order."""
        taken = []
        while not self.notifications.empty():
            taken.append(self.notifications.get_nowait())
        return taken

    async def close(self) -> None:
        await self.ws.close()
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task


@contextlib.asynccontextmanager
async def running_web(
    tmp_path: Path,
    clock: Callable[[], float] | None = None,
    machine: dict[str, Any] | None = None,
    write_timeout: float | None = None,
    **web: Any,
) -> AsyncIterator[Web]:
    """`web` are `[web]` keys (listen: a free loopback port); `machine` more machine keys."""
    async with running_daemon(tmp_path, **(machine or {})) as hostd:
        tokens = TokenStore(hostd.daemon.state_dir)
        token = await asyncio.to_thread(tokens.create, "test")
        config = WebConfig(**{"listen": "127.0.0.1:0", **web})
        extra: dict[str, Any] = {"clock": clock} if clock is not None else {}
        if write_timeout is not None:
            extra["write_timeout"] = write_timeout
        server = WebServer(build_methods(hostd.api), hostd.api.jobs, tokens, config, **extra)
        await server.start()
        try:
            async with aiohttp.ClientSession() as session:
                yield Web(hostd, server, token, session)
        finally:
            await server.close()


@pytest_asyncio.fixture
async def web(tmp_path: Path) -> AsyncIterator[Web]:
    async with running_web(tmp_path) as running:
        rpc = await running.hostd.client()
        await running.hostd.idle(rpc)
        await rpc.close()
        yield running


CHROMIUM = "/usr/bin/chromium"
FLAGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]

# ms: the longest any step waits for the page, a bound against a hang. 10 s ran out once
# at load average 14 on two cores (the from-line plan: job.recovery asks the board for
# its offsets and limits, and reads the file on an analysis worker).
TIMEOUT = 20_000
playwright.expect.set_options(timeout=TIMEOUT)


def chromium_path() -> str:
    """The page is tested in a real browser or not at all: a missing one is a failure."""
    if not os.path.exists(CHROMIUM):
        pytest.fail(
            f"{CHROMIUM} is missing: apt-get install chromium chromium-driver (.ci/run does)"
        )
    return CHROMIUM


# One chromium per test process, on the session's event loop: launching it (and
# Playwright's driver) for each test cost seconds of the two cores' time per test.
# Each test still gets a context of its own, as fresh as a new profile (no cookies,
# no storage, no cache), closed with its pages when the test ends. A test that uses
# `browser` runs on the session's loop: `pytest.mark.asyncio(loop_scope="session")`.
@pytest_asyncio.fixture(scope="session", loop_scope="session")
async def shared_chromium() -> AsyncIterator[playwright.Browser]:
    async with playwright.async_playwright() as p:
        launched = await p.chromium.launch(
            executable_path=chromium_path(), headless=True, args=FLAGS
        )
        try:
            yield launched
        finally:
            await launched.close()


@pytest_asyncio.fixture(loop_scope="session")
async def browser(
    shared_chromium: playwright.Browser,
) -> AsyncIterator[playwright.BrowserContext]:
    context = await shared_chromium.new_context(viewport={"width": 1280, "height": 900})
    context.set_default_timeout(TIMEOUT)
    try:
        yield context
    finally:
        await context.close()


async def screenshot(page: playwright.Page, tmp_path: Path, name: str) -> None:
    path = tmp_path / f"{name}.png"
    # No passing note over the page; from the top (a sticky header scrolled with the page
    # would sit half-way down a full-page shot).
    await page.evaluate("document.getElementById('toast').hidden = true; window.scrollTo(0, 0)")
    await page.screenshot(path=path, full_page=True)
    if where := os.environ.get("HOSTD_SCREENSHOTS"):
        await asyncio.to_thread(_keep, path, Path(where))


def _keep(path: Path, where: Path) -> None:
    where.mkdir(parents=True, exist_ok=True)
    shutil.copy(path, where / path.name)


async def log_in(page: playwright.Page, web: Web) -> None:
    await page.goto(f"{web.url}/login#token={web.token}")
    await page.wait_for_url(f"{web.url}/")
    expect = playwright.expect
    await expect(page.locator("#link")).to_have_text("live")
    await expect(page.locator("#supervisor")).to_have_text("idle")
