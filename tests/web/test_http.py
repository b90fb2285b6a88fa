"""The web API through a real aiohttp server on loopback: tokens, Origin, CSP, the one API."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import time
from collections.abc import Callable
from pathlib import Path

import aiohttp
import pytest
from structlog.testing import capture_logs

from hostd.api import client as client_module
from hostd.api.web import COOKIE
from hostd.machine.events import StatusChanged
from tests.web.conftest import Web, WsRpc, running_web

pytestmark = pytest.mark.asyncio


async def test_without_a_token_nothing_but_the_login_page_is_served(web: Web) -> None:
    s = web.session
    async with s.get(f"{web.url}/", allow_redirects=False) as r:
        assert r.status == 302 and r.headers["Location"] == "/login"
    for path in ("/static/app.js", "/session"):
        async with s.get(f"{web.url}{path}") as r:
            assert r.status == 401
    async with s.post(f"{web.url}/files/a.nc", data=b"G0 X1\n") as r:
        assert r.status == 401
    with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
        await s.ws_connect(f"{web.url}/api")
    assert refused.value.status == 401
    with pytest.raises(aiohttp.WSServerHandshakeError):
        await s.ws_connect(f"{web.url}/api", headers=web.auth("hostd_not-a-token"))
    async with s.get(f"{web.url}/login") as r:
        assert r.status == 200 and "<form" in await r.text()


async def test_every_response_carries_a_restrictive_csp(web: Web) -> None:
    for path, headers in (("/login", {}), ("/", web.auth()), ("/session", {})):
        async with web.session.get(f"{web.url}{path}", headers=headers) as r:
            csp = r.headers["Content-Security-Policy"]
            assert "default-src 'none'" in csp and "script-src 'self'" in csp
            assert "unsafe-inline" not in csp and "frame-ancestors 'none'" in csp
            assert r.headers["X-Content-Type-Options"] == "nosniff"


async def test_the_websocket_speaks_the_same_json_rpc_and_notifications(web: Web) -> None:
    api = await web.ws()
    try:
        assert (await api.call("daemon.info"))["machines"] == ["sim1"]
        assert (await api.call("machine.status", machine="sim1"))["supervisor"] == "idle"
        error = (await api.request("machine.status", machine="nope"))["error"]
        assert error["code"] == 1001
        await api.call("subscribe", topics=["status"], machine="sim1")
        note = await api.notification(lambda n: n["method"] == "status")
        assert note["params"]["machine"] == "sim1" and "snapshot" in note["params"]
    finally:
        await api.close()


async def test_a_tab_is_told_what_waited_before_the_web_server_closes(
    web: Web, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The daemon stopping closes the web server: a notification still waiting to be
    written with others (NOTICE_DELAY, an hour here) reaches the tab before its close."""
    monkeypatch.setattr(client_module, "NOTICE_DELAY", 3600.0)
    api = await web.ws()
    try:
        await api.call("subscribe", topics=["status"], machine="sim1")
        told = asyncio.Event()
        machine = web.hostd.daemon.machines["sim1"]
        # After the API's own listener: once this hears a status, the tab's is staged.
        unsubscribe = machine.hub.subscribe(
            lambda event: told.set() if isinstance(event, StatusChanged) else None
        )
        try:
            async with asyncio.timeout(10):
                await told.wait()
        finally:
            unsubscribe()
        api.queued()  # any that went out with subscribe's answer
        await web.server.close()
        async with asyncio.timeout(10):
            await api.closed.wait()  # everything the server sent is read
        told_tab = api.queued()
        assert any(n["method"] == "status" for n in told_tab), told_tab
    finally:
        await api.close()


async def test_a_login_sets_an_httponly_samesite_strict_cookie_that_opens_the_api(
    web: Web,
) -> None:
    # unsafe: the jar keeps cookies of a bare IP address (127.0.0.1), as a browser does.
    async with aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True)) as browser:
        async with browser.post(f"{web.url}/login", json={"token": "wrong"}) as r:
            assert r.status == 401
        async with browser.post(f"{web.url}/login", json={"token": web.token}) as r:
            assert r.status == 200
            cookie = r.cookies[COOKIE]
            assert cookie["httponly"] and cookie["samesite"] == "Strict"
            assert cookie["path"] == "/"
        api = WsRpc(await browser.ws_connect(f"{web.url}/api"))  # the jar carries the cookie
        try:
            assert (await api.call("machine.list"))[0]["id"] == "sim1"
        finally:
            await api.close()


async def test_a_bug_past_the_dispatcher_is_an_internal_error_and_the_tab_goes_on(
    web: Web, rpc_answer_fails_once: Callable[[], None]
) -> None:
    """The WebSocket takes requests through the same intake as the socket (intake.py)."""
    rpc_answer_fails_once()
    async with web.session.ws_connect(f"{web.url}/api", headers=web.auth()) as ws:
        await ws.send_str(json.dumps({"jsonrpc": "2.0", "id": 1, "method": "machine.list"}))
        assert json.loads((await ws.receive(timeout=10)).data) == {
            "jsonrpc": "2.0",
            "error": {"code": -32603, "message": "internal error"},
            "id": None,
        }
        await ws.send_str(json.dumps({"jsonrpc": "2.0", "id": 2, "method": "machine.list"}))
        reply = json.loads((await ws.receive(timeout=10)).data)
        assert reply["id"] == 2 and reply["result"][0]["id"] == "sim1"


async def test_a_websocket_from_another_origin_is_refused(web: Web) -> None:
    with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
        await web.ws(headers={**web.auth(), "Origin": "http://evil.example"})
    assert refused.value.status == 403
    same = await web.ws(headers={**web.auth(), "Origin": web.url})
    await same.close()


async def test_login_attempts_are_rate_limited_per_address(tmp_path: Path) -> None:
    now = [1000.0]
    async with running_web(tmp_path, clock=lambda: now[0], login_attempts=3) as web:
        for _ in range(3):
            async with web.session.post(f"{web.url}/login", json={"token": "guess"}) as r:
                assert r.status == 401
        async with web.session.post(f"{web.url}/login", json={"token": web.token}) as r:
            assert r.status == 429 and int(r.headers["Retry-After"]) > 0
        now[0] += 61
        async with web.session.post(f"{web.url}/login", json={"token": web.token}) as r:
            assert r.status == 200


async def test_an_upload_over_http_lands_in_the_jobs_directory_under_the_same_rules(
    web: Web,
) -> None:
    body = b"".join(f"G1 X{i % 50} Y{i % 7} F600\n".encode() for i in range(200_000))
    async with web.session.post(f"{web.url}/files/big.nc", data=body, headers=web.auth()) as r:
        assert r.status == 200, await r.text()
        assert await r.json() == {"name": "big.nc", "size": len(body)}
    assert (web.hostd.jobs / "big.nc").read_bytes() == body
    for bad in (".hidden", "a%5Cb"):
        async with web.session.post(f"{web.url}/files/{bad}", data=b"x", headers=web.auth()) as r:
            assert r.status == 400
    async with web.session.post(
        f"{web.url}/files/x.nc", data=b"x", headers={**web.auth(), "Origin": "http://evil.example"}
    ) as r:
        assert r.status == 403
    api = await web.ws()
    try:
        assert "big.nc" in [f["name"] for f in await api.call("file.list")]
    finally:
        await api.close()


async def test_watch_only_serves_reads_and_refuses_control_and_uploads(tmp_path: Path) -> None:
    async with running_web(tmp_path, control=False) as web:
        async with web.session.get(f"{web.url}/session", headers=web.auth()) as r:
            assert await r.json() == {"control": False}
        async with web.session.post(f"{web.url}/files/a.nc", data=b"G0\n", headers=web.auth()) as r:
            assert r.status == 403
        api = await web.ws()
        try:
            assert (await api.call("machine.status", machine="sim1"))["id"] == "sim1"
            assert await api.call("macro.list") == []  # a read: listed, never run
            error = (await api.request("macro.run", machine="sim1", name="x"))["error"]
            assert error["code"] == -32601
            for method in ("machine.feedhold", "job.cancel", "machine.reset"):
                error = (await api.request(method, machine="sim1"))["error"]
                assert error["code"] == -32601 and "watch only" in error["message"]
        finally:
            await api.close()


async def test_a_tab_that_falls_behind_its_queue_is_dropped_and_others_go_on(web: Web) -> None:
    slow, other = await web.ws(), await web.ws()
    try:
        await slow.call("daemon.info")
        await other.call("daemon.info")
        behind = next(c for c in web.server.clients if c.id == 1)
        # A burst of notifications within one loop pass: more than the bounded queue holds.
        for _ in range(1001):
            behind.notify("status", {"machine": "sim1"})
        assert behind.closed
        async with asyncio.timeout(5):
            await slow.closed.wait()
        assert (await other.call("machine.status", machine="sim1"))["id"] == "sim1"
    finally:
        await slow.close()
        await other.close()


async def _stalled_tab(web: Web, topics: list[str]) -> socket.socket:
    """A WebSocket opened by hand on a socket with a tiny receive buffer, then never read.

    Like a browser tab frozen in the background: its subscription goes on
    producing, and nothing is taken off the connection.
    """
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.setblocking(False)
    loop = asyncio.get_running_loop()
    await loop.sock_connect(sock, ("127.0.0.1", web.server.port))
    request = (
        "GET /api HTTP/1.1\r\n"
        f"Host: 127.0.0.1:{web.server.port}\r\n"
        "Upgrade: websocket\r\nConnection: Upgrade\r\n"
        "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
        f"Authorization: Bearer {web.token}\r\n\r\n"
    )
    await loop.sock_sendall(sock, request.encode())
    answer = b""
    while b"\r\n\r\n" not in answer:
        answer += await loop.sock_recv(sock, 1)  # byte by byte: not one frame byte more
    assert answer.startswith(b"HTTP/1.1 101"), answer
    payload = json.dumps(
        {
            "jsonrpc": "2.0",
            "id": 1,
            "method": "subscribe",
            "params": {"topics": topics, "machine": "sim1"},
        }
    ).encode()
    mask = os.urandom(4)  # a client's frames are masked (RFC 6455 5.3)
    head = bytes([0x81, 0x80 | 126]) + len(payload).to_bytes(2, "big") + mask
    body = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
    await loop.sock_sendall(sock, head + body)
    return sock


async def test_a_tab_that_never_reads_is_dropped_and_the_job_streams_on(tmp_path: Path) -> None:
    # A frozen tab is dropped once one frame cannot be sent within the write timeout
    # (10 s in the daemon; half a second here) or its queue fills, whichever first.
    async with running_web(tmp_path, write_timeout=0.5) as web:
        rpc = await web.hostd.client()
        await web.hostd.idle(rpc)
        await rpc.close()
        stalled = await _stalled_tab(web, ["console", "status", "job"])
        other = await web.ws()
        try:
            frozen = min(web.server.clients, key=lambda c: c.id)  # it connected first
            # The kernel would otherwise buffer megabytes for it on loopback: a phone on
            # poor Wi-Fi has no such room. A fixed send buffer stops the autotuning.
            server_side = frozen._transport.get_extra_info("socket")  # type: ignore[attr-defined]
            server_side.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
            dropped = asyncio.Event()
            frozen.on_disconnect.append(dropped.set)
            # Moves of ~4.5 ms on the daemon's simulated board, each: the 48 in its
            # planner (about 0.2 s) outlast a loaded test machine's pause, so the job
            # cannot underflow. What the frozen tab is sent fills its buffers (the two
            # sockets, the transport's 64 KiB, aiohttp's 64 KiB before it drains) by
            # about the 700th line: the write then waits, and the tab is dropped half a
            # second later, with 1,200 lines well before the job's end. (At F6000,
            # moves of 1.4 ms, 67 ms of planner: a loaded machine underflowed the job.)
            lines = "".join(f"G1 X{i % 2} Y{i % 2} F2000 (tab test {i:05d})\n" for i in range(1200))
            await other.call("file.upload", name="long.nc", data=lines)
            await other.call("subscribe", topics=["job"], machine="sim1")
            job = (await other.call("job.start", machine="sim1", file="long.nc"))["job"]
            async with asyncio.timeout(30):
                await dropped.wait()
                running = await other.call("job.get", job=job)
                assert running["state"] == "running", running  # dropped while the job streams
                while True:
                    note = await other.notifications.get()
                    if note["method"] == "job" and note["params"]["job"]["state"] != "running":
                        break
            assert note["params"]["job"]["id"] == job
            assert note["params"]["job"]["state"] == "completed"
            assert note["params"]["job"]["lines_acked"] == 1200
            assert web.server.clients == [c for c in web.server.clients if c is not frozen]
            assert (await other.call("machine.status", machine="sim1"))["id"] == "sim1"
        finally:
            stalled.close()
            await other.close()


async def test_a_request_naming_an_unknown_host_is_refused_against_dns_rebinding(
    tmp_path: Path,
) -> None:
    async with running_web(tmp_path, hosts=["cnc.shop.lan"]) as web:
        port = web.server.port

        async def status(host: str) -> int:
            headers = {**web.auth(), "Host": host}
            async with web.session.get(f"{web.url}/session", headers=headers) as response:
                return response.status

        # A page on a name the attacker controls, resolved to this machine, names it.
        assert await status(f"evil.example:{port}") == 421
        assert await status(f"localhost:{port}") == 200
        assert await status(f"127.0.0.1:{port}") == 200
        assert await status(f"cnc.shop.lan:{port}") == 200  # [web] hosts
        assert await status(f"CNC.Shop.LAN:{port}") == 200


async def test_a_flood_of_requests_for_an_unknown_host_is_refused_each_and_logged_counted(
    tmp_path: Path,
) -> None:
    """Every request is refused; the log counts them all in a record a second at most
    (the last at the server's close), where a line each would be the attacker's to write."""
    with capture_logs() as logs:
        async with running_web(tmp_path) as web:
            headers = {**web.auth(), "Host": f"evil.example:{web.server.port}"}
            started = time.monotonic()
            for _ in range(300):
                async with web.session.get(f"{web.url}/session", headers=headers) as response:
                    assert response.status == 421
            elapsed = time.monotonic() - started
    records = [e for e in logs if e["event"] == "web request for an unknown host refused"]
    assert sum(e.get("repeats", 1) for e in records) == 300
    assert len(records) <= 2 + elapsed
    assert records[0]["host"] == f"evil.example:{web.server.port}"


@pytest.mark.parametrize("compress", [0, 15], ids=["plain", "deflate"])
async def test_messages_of_every_size_arrive_whole_as_sent(web: Web, compress: int) -> None:
    """Frames the daemon makes itself (plain) and aiohttp's (deflate) read back the same:
    short (7-bit length), medium (16-bit, rpc.discover) and over 64 KiB (64-bit: an
    unknown method's long name, which its error repeats)."""
    long_name = "x" * 70_000
    methods = ["daemon.info", "rpc.discover", long_name]
    async with web.session.ws_connect(
        f"{web.url}/api", headers=web.auth(), compress=compress
    ) as ws:
        for i in range(30):
            request = {"jsonrpc": "2.0", "id": i, "method": methods[i % 3]}
            await ws.send_str(json.dumps(request))
        frames = [(await ws.receive(timeout=10)).data for _ in range(30)]
    answers = {msg["id"]: msg.get("result", msg.get("error")) for msg in map(json.loads, frames)}
    assert sorted(answers) == list(range(30))
    bands = {(n >= 126) + (n >= 1 << 16) for n in (len(frame.encode()) for frame in frames)}
    assert bands == {0, 1, 2}
    for i, result in answers.items():
        assert result == answers[i % 3]  # the same method, the same answer, every time
    assert answers[0]["machines"] == ["sim1"] and answers[1]["openrpc"]
    assert answers[2] == {"code": -32601, "message": f"method not found: {long_name}"}
