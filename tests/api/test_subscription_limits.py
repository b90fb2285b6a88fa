"""Subscriptions through the real socket and WebSocket: bounded per client and in all, and
one notification encoded once, the same bytes to every subscriber."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import pytest

from hostd.api import methods
from hostd.api.methods import subscriptions
from hostd.api.rpc import encode_notification
from tests.daemon.conftest import RpcFailure
from tests.web.conftest import running_web

pytestmark = pytest.mark.asyncio


async def test_a_tab_subscribing_in_a_loop_is_stopped_at_the_per_client_limit(
    tmp_path: Path,
) -> None:
    async with running_web(tmp_path, control=False) as web:  # a watch-only tab may subscribe
        tab = await web.ws()
        try:
            ids = [
                (await tab.call("subscribe", topics=["status", "job"], machine="sim1"))[
                    "subscription"
                ]
                for _ in range(methods.MAX_SUBSCRIPTIONS_PER_CLIENT)
            ]
            refused = await tab.request("subscribe", topics=["status"], machine="sim1")
            assert refused["error"]["code"] == -32000
            assert "32 per client" in refused["error"]["message"]
            assert len(web.hostd.api.subscriptions) == methods.MAX_SUBSCRIPTIONS_PER_CLIENT
            # Another client is not the loop's victim; the tab can unsubscribe and go on.
            other = await web.hostd.client()
            await other.call("subscribe", topics=["status"], machine="sim1")
            await tab.call("unsubscribe", subscription=ids[0])
            await tab.call("subscribe", topics=["status"], machine="sim1")
            await other.close()
        finally:
            await tab.close()
        # Gone with the clients.
        async with asyncio.timeout(10):
            while len(web.hostd.api.subscriptions) > 0:  # noqa: ASYNC110 (no event for it)
                await asyncio.sleep(0.02)


async def test_the_total_limit_holds_across_clients(tmp_path: Path) -> None:
    async with running_web(tmp_path) as web:
        subs = web.hostd.api.subscriptions
        subs.max_total = len(subs) + 3
        first, second = await web.hostd.client(), await web.hostd.client()
        for _ in range(2):
            await first.call("subscribe", topics=["status"])
        await second.call("subscribe", topics=["status"])
        with pytest.raises(RpcFailure) as refused:
            await second.call("subscribe", topics=["job"])
        assert refused.value.code == -32000 and "in all" in refused.value.message
        await first.close()
        await second.close()


async def raw_lines(path: str, subscribe: dict[str, Any]) -> tuple[asyncio.StreamReader, Any]:
    reader, writer = await asyncio.open_unix_connection(path, limit=1 << 22)
    request = {"jsonrpc": "2.0", "id": 1, "method": "subscribe", "params": subscribe}
    writer.write(json.dumps(request).encode() + b"\n")
    assert b'"result"' in await reader.readline()
    return reader, writer


async def test_a_notification_is_encoded_once_and_every_subscriber_gets_the_same_bytes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    encoded: list[bytes] = []
    real = encode_notification

    def counting(method: str, params: Any) -> bytes:
        line = real(method, params)
        if method == "job":
            encoded.append(line)
        return line

    monkeypatch.setattr(subscriptions, "encode_notification", counting)
    async with running_web(tmp_path) as web:
        rpc = await web.hostd.client()
        await web.hostd.idle(rpc)
        wanted = {"topics": ["job"], "machine": "sim1"}
        sockets = [await raw_lines(web.hostd.socket, wanted) for _ in range(3)]
        tabs = [
            await web.session.ws_connect(f"{web.url}/api", headers=web.auth()) for _ in range(2)
        ]
        for tab in tabs:
            await tab.send_str(
                json.dumps({"jsonrpc": "2.0", "id": 1, "method": "subscribe", "params": wanted})
            )
            assert "result" in json.loads((await tab.receive()).data)
        await rpc.call("file.upload", name="short.nc", data="G1 X1 F3000\nG1 X0\n" * 50)
        await rpc.call("job.start", machine="sim1", file="short.nc")

        def final(line: bytes) -> bool:
            return bool(json.loads(line)["params"]["job"]["state"] == "completed")

        received: list[list[bytes]] = []
        async with asyncio.timeout(20):
            for reader, _ in sockets:
                lines: list[bytes] = []
                while not lines or not final(lines[-1]):
                    lines.append((await reader.readline()).rstrip(b"\n"))
                received.append(lines)
            for tab in tabs:
                frames: list[bytes] = []
                while not frames or not final(frames[-1]):
                    frames.append((await tab.receive()).data.encode())
                received.append(frames)
        # Five subscribers, one encoding of each notification, the same bytes everywhere.
        assert all(r == received[0] for r in received)
        assert received[0] == encoded[: len(received[0])]
        assert len(encoded) == len(received[0])
        for _, writer in sockets:
            writer.close()
        for tab in tabs:
            await tab.close()
        await rpc.close()
