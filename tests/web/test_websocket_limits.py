"""The `/api` WebSocket's bounds (websocket.py, docs/web.md): at most `max_clients` tabs
are connected at once, one more is refused (503) before its handshake, and a frame over
the socket's 1 MiB line limit closes the WebSocket (1009) without any of it being run."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import aiohttp
import pytest

from hostd.api.methods import build_methods
from hostd.api.server import MAX_LINE
from hostd.api.tokens import TokenStore
from hostd.api.web import WebServer
from hostd.config import WebConfig
from tests.daemon.conftest import running_daemon
from tests.web.conftest import Web, WsRpc

pytestmark = pytest.mark.asyncio


async def test_one_tab_past_max_clients_is_refused_before_its_handshake(tmp_path: Path) -> None:
    async with running_daemon(tmp_path) as hostd:
        tokens = TokenStore(hostd.daemon.state_dir)
        token = await asyncio.to_thread(tokens.create, "test")
        config = WebConfig(listen="127.0.0.1:0")
        server = WebServer(build_methods(hostd.api), hostd.api.jobs, tokens, config, max_clients=2)
        await server.start()
        try:
            url = f"http://127.0.0.1:{server.port}/api"
            auth = {"Authorization": f"Bearer {token}"}
            async with aiohttp.ClientSession() as session:
                tabs = [WsRpc(await session.ws_connect(url, headers=auth)) for _ in range(2)]
                try:
                    for tab in tabs:
                        assert (await tab.call("machine.list"))[0]["id"] == "sim1"
                    with pytest.raises(aiohttp.WSServerHandshakeError) as full:
                        await session.ws_connect(url, headers=auth)
                    assert full.value.status == 503
                    assert len(server.clients) == 2
                finally:
                    for tab in tabs:
                        await tab.close()
        finally:
            await server.close()


async def test_a_frame_over_the_line_limit_closes_the_websocket_unrun(web: Web) -> None:
    async with web.session.ws_connect(f"{web.url}/api", headers=web.auth()) as ws:
        # A request the server would answer, padded past the limit with a param.
        padding = "x" * MAX_LINE
        request = {"jsonrpc": "2.0", "id": 1, "method": "file.upload"}
        request["params"] = {"name": "big.nc", "data": padding}
        await ws.send_str(json.dumps(request))
        message = await ws.receive(timeout=10)
        assert message.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED), message
        assert ws.close_code == aiohttp.WSCloseCode.MESSAGE_TOO_BIG
    assert not (web.hostd.jobs / "big.nc").exists()
