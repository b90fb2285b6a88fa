"""Who may log in to the dashboard and how long a login counts (docs/web.md, auth.py):
a login posted from another site is refused and sets no cookie (login CSRF); a session
unused for `session_expiry` seconds has ended, while one in use goes on; and a revoked
token's browser session is refused on its very next request, not only once the token
watcher's next look (REVOKE_POLL) has ended it."""

from __future__ import annotations

from pathlib import Path

import aiohttp
import pytest

from hostd.api.tokens import TokenStore
from hostd.api.web import COOKIE, auth
from tests.web.conftest import Web, running_web

pytestmark = pytest.mark.asyncio


def jar() -> aiohttp.CookieJar:
    return aiohttp.CookieJar(unsafe=True)  # keeps cookies of 127.0.0.1, as a browser does


async def test_a_login_posted_from_another_site_is_refused_and_sets_no_cookie(web: Web) -> None:
    async with aiohttp.ClientSession(cookie_jar=jar()) as browser:
        async with browser.post(
            f"{web.url}/login", json={"token": web.token}, headers={"Origin": "http://evil.example"}
        ) as r:
            assert r.status == 403
            assert COOKIE not in r.cookies
        async with browser.get(f"{web.url}/session") as r:
            assert r.status == 401  # no session came of it
        # From the page's own origin, the same login works.
        async with browser.post(
            f"{web.url}/login", json={"token": web.token}, headers={"Origin": web.url}
        ) as r:
            assert r.status == 200
        async with browser.get(f"{web.url}/session") as r:
            assert r.status == 200


async def test_a_revoked_tokens_session_is_refused_before_the_watcher_looks(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The watcher would end the session within REVOKE_POLL; here it never gets to.
    monkeypatch.setattr(auth, "REVOKE_POLL", 3600.0)
    async with running_web(tmp_path) as web, aiohttp.ClientSession(cookie_jar=jar()) as browser:
        async with browser.post(f"{web.url}/login", json={"token": web.token}) as r:
            assert r.status == 200
        async with browser.get(f"{web.url}/session") as r:
            assert r.status == 200
        # `hostd token revoke`, another process: another TokenStore on the same file.
        cli = TokenStore(web.hostd.daemon.state_dir)
        assert cli.revoke(next(r.id for r in cli.records() if r.name == "test"))
        async with browser.get(f"{web.url}/session") as r:
            assert r.status == 401
        with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
            await browser.ws_connect(f"{web.url}/api")
        assert refused.value.status == 401


async def test_a_session_unused_for_session_expiry_has_ended(tmp_path: Path) -> None:
    now = [1000.0]
    async with (
        running_web(tmp_path, clock=lambda: now[0], session_expiry=60.0) as web,
        aiohttp.ClientSession(cookie_jar=jar()) as browser,
    ):
        async with browser.post(f"{web.url}/login", json={"token": web.token}) as r:
            assert r.status == 200
        for _ in range(3):  # in use: each request counts as use, so it goes on
            now[0] += 50
            async with browser.get(f"{web.url}/session") as r:
                assert r.status == 200
        now[0] += 61  # unused for longer than session_expiry
        async with browser.get(f"{web.url}/session") as r:
            assert r.status == 401
        with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
            await browser.ws_connect(f"{web.url}/api")
        assert refused.value.status == 401
        # The token itself still logs in.
        async with browser.post(f"{web.url}/login", json={"token": web.token}) as r:
            assert r.status == 200
        async with browser.get(f"{web.url}/session") as r:
            assert r.status == 200
