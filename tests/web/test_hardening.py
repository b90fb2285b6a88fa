"""The web server from outside, through real sockets: revoked tokens, sessions, slow and idle
connections, connection caps, a trusted proxy, and uploads that fail half-way."""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
from collections.abc import AsyncIterator
from pathlib import Path

import aiohttp
import pytest
from structlog.testing import capture_logs

from hostd.api.tokens import TokenStore
from hostd.api.uploads import STAGING
from hostd.api.web import COOKIE
from tests.web.conftest import Web, WsRpc, running_web

pytestmark = pytest.mark.asyncio

WAIT = 10.0


def jar() -> aiohttp.CookieJar:
    return aiohttp.CookieJar(unsafe=True)  # keeps cookies of 127.0.0.1, as a browser does


async def login(web: Web, browser: aiohttp.ClientSession, **headers: str) -> str:
    async with browser.post(f"{web.url}/login", json={"token": web.token}, headers=headers) as r:
        assert r.status == 200, await r.text()
        return r.cookies[COOKIE].value


async def test_the_cookie_holds_a_session_id_not_the_token_and_logout_ends_it(web: Web) -> None:
    async with aiohttp.ClientSession(cookie_jar=jar()) as browser:
        session = await login(web, browser)
    assert session and web.token not in session and session not in web.token
    cookie = {"Cookie": f"{COOKIE}={session}"}
    async with web.session.get(f"{web.url}/session", headers=cookie) as r:
        assert r.status == 200
    # The raw token in the cookie is no session.
    async with web.session.get(
        f"{web.url}/session", headers={"Cookie": f"{COOKIE}={web.token}"}
    ) as r:
        assert r.status == 401
    async with web.session.post(f"{web.url}/logout", headers=cookie) as r:
        assert r.status == 200
    # Ended on the server: a copy of the cookie kept elsewhere is worth nothing now.
    async with web.session.get(f"{web.url}/session", headers=cookie) as r:
        assert r.status == 401


async def test_revoking_a_token_closes_its_websockets_and_ends_its_sessions(web: Web) -> None:
    other = TokenStore(web.hostd.daemon.state_dir).create("another")
    async with aiohttp.ClientSession(cookie_jar=jar()) as browser:
        await login(web, browser)
        by_cookie = WsRpc(await browser.ws_connect(f"{web.url}/api"))
        by_bearer = await web.ws()
        unrelated = await web.ws(headers=web.auth(other))
        try:
            for api in (by_cookie, by_bearer, unrelated):
                await api.call("subscribe", topics=["status"], machine="sim1")
            # `hostd token revoke` is another process: another TokenStore on the same file.
            cli = TokenStore(web.hostd.daemon.state_dir)
            revoked = next(r.id for r in cli.records() if r.name == "test")
            assert cli.revoke(revoked)
            async with asyncio.timeout(WAIT):
                await by_cookie.closed.wait()
                await by_bearer.closed.wait()
            async with browser.get(f"{web.url}/session") as r:
                assert r.status == 401
            async with web.session.get(f"{web.url}/session", headers=web.auth()) as r:
                assert r.status == 401
            # Another token's tab goes on.
            assert (await unrelated.call("machine.status", machine="sim1"))["id"] == "sim1"
            assert not unrelated.closed.is_set()
        finally:
            for api in (by_cookie, by_bearer, unrelated):
                await api.close()


async def connect(port: int, source: str = "127.0.0.1") -> socket.socket:
    sock = socket.socket()
    sock.setblocking(False)
    sock.bind((source, 0))
    await asyncio.get_running_loop().sock_connect(sock, ("127.0.0.1", port))
    return sock


async def closed_by_server(sock: socket.socket) -> None:
    """Until the server ends the connection (EOF or reset); whatever it sent is read away."""
    loop = asyncio.get_running_loop()
    async with asyncio.timeout(WAIT):
        with contextlib.suppress(ConnectionResetError):
            while await loop.sock_recv(sock, 65536):
                pass


async def served(sock: socket.socket, web: Web, path: str = "/session") -> bytes:
    """One keep-alive request on `sock`, and its response head (the connection stays)."""
    loop = asyncio.get_running_loop()
    request = f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {web.token}\r\n\r\n"
    await loop.sock_sendall(sock, request.encode())
    answer = b""
    async with asyncio.timeout(WAIT):
        while b"\r\n\r\n" not in answer:
            chunk = await loop.sock_recv(sock, 65536)
            assert chunk, "closed instead of served"
            answer += chunk
    return answer


async def test_headers_sent_too_slowly_or_not_at_all_close_the_connection(tmp_path: Path) -> None:
    async with running_web(tmp_path, header_timeout=0.3) as web:
        silent = await connect(web.server.port or 0)
        slow = await connect(web.server.port or 0)
        loop = asyncio.get_running_loop()
        with capture_logs() as logs:
            await loop.sock_sendall(slow, b"GET /session HTTP/1.1\r\nHost: 127.0.0.1\r\nX-A: ")
            for sock in (silent, slow):
                await closed_by_server(sock)
                sock.close()
        late = [
            e for e in logs if e["event"] == "web connection closed: no request headers in time"
        ]
        assert len(late) == 2
        assert web.server.guard.open == 0


async def test_an_idle_connection_is_closed_after_its_last_request(tmp_path: Path) -> None:
    async with running_web(tmp_path, idle_timeout=0.3) as web:
        sock = await connect(web.server.port or 0)
        assert (await served(sock, web)).startswith(b"HTTP/1.1 200")
        await closed_by_server(sock)
        sock.close()


@contextlib.asynccontextmanager
async def held(web: Web, source: str, n: int) -> AsyncIterator[list[socket.socket]]:
    """`n` connections from `source`, each served once and then kept open."""
    socks = []
    try:
        for _ in range(n):
            sock = await connect(web.server.port or 0, source)
            socks.append(sock)
            assert (await served(sock, web)).startswith(b"HTTP/1.1 200")
        yield socks
    finally:
        for sock in socks:
            sock.close()


async def test_connections_are_capped_per_address_and_in_all(tmp_path: Path) -> None:
    caps = {"max_connections": 5, "max_connections_per_address": 3}
    async with running_web(tmp_path, **caps) as web:
        rpc = await web.hostd.client()
        with capture_logs() as logs:
            async with held(web, "127.0.0.1", 3):
                # A fourth from 127.0.0.1: over its address's cap, closed unread.
                one_more = await connect(web.server.port or 0, "127.0.0.1")
                await closed_by_server(one_more)
                one_more.close()
                async with held(web, "127.0.0.2", 2):
                    # From a third address: the total is reached.
                    third = await connect(web.server.port or 0, "127.0.0.3")
                    await closed_by_server(third)
                    third.close()
                    # The Unix socket is another server: never short of a connection.
                    assert (await rpc.call("machine.status", machine="sim1"))["id"] == "sim1"
            # Those closed, the third address is served.
            async with held(web, "127.0.0.3", 1):
                pass
        refused = [e for e in logs if e["event"] == "web connections refused"]
        assert refused and "max_connections_per_address" in refused[0]["over"]
        assert web.server.guard.refused == 2
        await rpc.close()


async def test_behind_a_trusted_proxy_the_forwarded_client_is_rate_limited_not_the_proxy(
    tmp_path: Path,
) -> None:
    now = [0.0]
    settings = {"login_attempts": 2, "trusted_proxies": ["127.0.0.1/32"]}
    async with running_web(tmp_path, clock=lambda: now[0], **settings) as web:
        url = f"{web.url}/login"
        for client in ("10.0.0.1", "10.0.0.2"):
            forwarded = {"X-Forwarded-For": f"{client}, 127.0.0.1"}
            for _ in range(2):
                async with web.session.post(url, json={"token": "no"}, headers=forwarded) as r:
                    assert r.status == 401
            async with web.session.post(url, json={"token": "no"}, headers=forwarded) as r:
                assert r.status == 429  # this client, not the proxy's other clients
        # The browser spoke https to the proxy: its Origin says so, and so does the proxy.
        proxied = {
            "X-Forwarded-For": "10.0.0.3",
            "X-Forwarded-Proto": "https",
            "Origin": f"https://127.0.0.1:{web.server.port}",
        }
        async with aiohttp.ClientSession(cookie_jar=jar()) as browser:
            async with browser.post(url, json={"token": web.token}, headers=proxied) as r:
                assert r.status == 200
                assert r.cookies[COOKIE]["secure"]  # https at the browser: a Secure cookie
            session = r.cookies[COOKIE].value
        ws = await web.session.ws_connect(
            f"{web.url}/api", headers={**proxied, "Cookie": f"{COOKIE}={session}"}
        )
        api = WsRpc(ws)
        try:
            assert (await api.call("machine.list"))[0]["id"] == "sim1"
        finally:
            await api.close()


async def test_without_trusted_proxies_forwarded_headers_are_ignored(tmp_path: Path) -> None:
    now = [0.0]
    async with running_web(tmp_path, clock=lambda: now[0], login_attempts=2) as web:
        url = f"{web.url}/login"
        for n in range(2):
            spoofed = {"X-Forwarded-For": f"10.0.0.{n}"}
            async with web.session.post(url, json={"token": "no"}, headers=spoofed) as r:
                assert r.status == 401
        # A new X-Forwarded-For does not buy another attempt.
        async with web.session.post(
            url, json={"token": "no"}, headers={"X-Forwarded-For": "10.9.9.9"}
        ) as r:
            assert r.status == 429
        proxied = {"X-Forwarded-Proto": "https", "Origin": f"https://127.0.0.1:{web.server.port}"}
        with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
            await web.session.ws_connect(f"{web.url}/api", headers={**proxied, **web.auth()})
        assert refused.value.status == 403


def staging(web: Web) -> list[str]:
    directory = Path(web.hostd.daemon.jobs_dir) / STAGING
    return sorted(p.name for p in directory.iterdir()) if directory.exists() else []


async def test_an_upload_cut_off_half_way_leaves_no_staging(tmp_path: Path) -> None:
    async with running_web(tmp_path) as web:
        loop = asyncio.get_running_loop()
        sock = await connect(web.server.port or 0)
        head = (
            "POST /files/cut.nc HTTP/1.1\r\nHost: 127.0.0.1\r\n"
            f"Authorization: Bearer {web.token}\r\nContent-Length: {10 << 20}\r\n\r\n"
        )
        with capture_logs() as logs:
            await loop.sock_sendall(sock, head.encode() + b"G0 X1\n" * (500 << 10))
            async with asyncio.timeout(WAIT):
                while not staging(web):  # noqa: ASYNC110 (the file system has no event)
                    await asyncio.sleep(0.02)
            sock.close()  # the sender gives up half-way
            async with asyncio.timeout(WAIT):
                while not any(e["event"] == "web upload failed; staging removed" for e in logs):  # noqa: ASYNC110
                    await asyncio.sleep(0.02)
        assert staging(web) == []
        async with web.session.get(f"{web.url}/files/cut.nc", headers=web.auth()) as r:
            assert r.status == 404


async def test_an_upload_past_the_quota_leaves_no_staging(tmp_path: Path) -> None:
    async with running_web(tmp_path, machine={"daemon": {"jobs_quota": 4 << 20}}) as web:
        body = b"G0 X1\n" * (1 << 20)  # 6 MiB
        async with web.session.post(f"{web.url}/files/big.nc", data=body, headers=web.auth()) as r:
            assert r.status == 507
        assert staging(web) == []


async def test_a_program_is_served_as_it_is_and_a_link_or_fifo_never(
    web: Web, tmp_path: Path
) -> None:
    """The preview's `GET /files/<name>`: a job file's bytes; a link planted in the jobs
    directory (to a file the daemon may read and the browser may not) or a FIFO is 404,
    checked on what was opened, not on the name beforehand (hostd/machine/jobfile.py)."""
    jobs = Path(web.hostd.daemon.jobs_dir)
    (jobs / "part.nc").write_bytes(b"G0 X1\nG1 Y2 F300\n")
    secret = tmp_path / "secret.txt"
    secret.write_text("not for the browser\n")
    (jobs / "link.nc").symlink_to(secret)
    os.mkfifo(jobs / "fifo.nc")
    async with web.session.get(f"{web.url}/files/part.nc", headers=web.auth()) as r:
        assert r.status == 200
        assert r.headers["Content-Type"] == "text/plain; charset=utf-8"
        assert await r.read() == b"G0 X1\nG1 Y2 F300\n"
    for name in ("link.nc", "fifo.nc", "none.nc"):
        async with asyncio.timeout(WAIT):
            async with web.session.get(f"{web.url}/files/{name}", headers=web.auth()) as r:
                assert r.status == 404, name
                assert "not for the browser" not in await r.text()
