"""A whole daemon (a simulated machine) with the web server on a loopback port, and a token."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiohttp
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
