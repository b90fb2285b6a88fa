"""Forwarded headers are believed only from `[web] trusted_proxies` (docs/web.md,
addresses.py): with proxies configured, a client that is not one of them cannot buy more
login attempts with a made-up `X-Forwarded-For`, nor pass the Origin check by claiming
https with `X-Forwarded-Proto`; and behind a trusted proxy the client is the last address
it appended, whatever the client itself wrote further left."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import aiohttp
import pytest

from tests.web.conftest import running_web

pytestmark = pytest.mark.asyncio


async def test_forwarded_headers_from_a_peer_that_is_not_a_trusted_proxy_are_ignored(
    tmp_path: Path,
) -> None:
    now = [0.0]
    settings: dict[str, Any] = {
        "login_attempts": 2,
        "trusted_proxies": ["10.0.0.0/8"],
    }  # not 127.0.0.1
    async with running_web(tmp_path, clock=lambda: now[0], **settings) as web:
        url = f"{web.url}/login"
        for n in range(2):
            spoofed = {"X-Forwarded-For": f"10.0.0.{n + 1}"}
            async with web.session.post(url, json={"token": "no"}, headers=spoofed) as r:
                assert r.status == 401
        spoofed = {"X-Forwarded-For": "10.9.9.9"}
        async with web.session.post(url, json={"token": web.token}, headers=spoofed) as r:
            assert r.status == 429  # the peer's own address has had its attempts
        claimed = {"X-Forwarded-Proto": "https", "Origin": f"https://127.0.0.1:{web.server.port}"}
        with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
            await web.session.ws_connect(f"{web.url}/api", headers={**claimed, **web.auth()})
        assert refused.value.status == 403


async def test_behind_a_trusted_proxy_the_clients_own_forwarded_claims_are_ignored(
    tmp_path: Path,
) -> None:
    now = [0.0]
    settings: dict[str, Any] = {"login_attempts": 2, "trusted_proxies": ["127.0.0.1/32"]}
    async with running_web(tmp_path, clock=lambda: now[0], **settings) as web:
        url = f"{web.url}/login"
        for n in range(3):
            # The proxy appended 10.0.0.5, the client; the client wrote the rest itself.
            forwarded = {"X-Forwarded-For": f"192.0.2.{n + 1}, 10.0.0.5"}
            async with web.session.post(url, json={"token": "no"}, headers=forwarded) as r:
                assert r.status == (401 if n < 2 else 429)
