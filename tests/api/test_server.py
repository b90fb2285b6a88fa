"""The API socket end to end: real connections, real framing, real peers."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import stat
import threading
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import pytest
from structlog.testing import capture_logs

from hostd.api import client as client_module
from hostd.api.peer import AccessPolicy
from hostd.api.server import ApiServer
from hostd.api.socketfile import SocketPathError

from .conftest import TIMEOUT, Conn, Harness, serving

pytestmark = pytest.mark.asyncio

MiB = 1 << 20


def by_id(responses: list[dict[str, Any]]) -> dict[Any, dict[str, Any]]:
    return {r["id"]: r for r in responses}


# --- answers ----------------------------------------------------------------


async def test_a_request_is_answered_with_its_result_and_id(conn: Conn) -> None:
    assert await conn.call("echo", {"text": "hi"}, id="abc") == {
        "jsonrpc": "2.0",
        "result": {"text": "hi"},
        "id": "abc",
    }
    assert (await conn.call("add", {"a": 2, "b": 3}, id=7))["result"] == 5


async def test_the_handler_sees_the_calling_client_from_its_credentials(conn: Conn) -> None:
    assert (await conn.call("whoami"))["result"] == {
        "pid": os.getpid(),
        "uid": os.getuid(),
        "gid": os.getgid(),
    }


async def test_empty_lines_are_ignored(conn: Conn) -> None:
    await conn.send_raw(b"\n\r\n   \n")
    assert (await conn.call("count", id=1))["id"] == 1


async def test_a_notification_runs_but_gets_no_answer(conn: Conn, harness: Harness) -> None:
    await conn.send({"jsonrpc": "2.0", "method": "count"})
    await conn.send({"jsonrpc": "2.0", "method": "no.such.method"})
    await conn.send({"jsonrpc": "2.0", "method": "boom"})
    await conn.send({"jsonrpc": "2.0", "method": "add", "params": {"a": "x"}})
    # Requests run concurrently, so only the answers' order on the wire is pinned:
    # the first line back is the answer to the first request that has an id.
    assert (await conn.call("count", id=2))["id"] == 2
    assert await conn.call("count", id=3) == {"jsonrpc": "2.0", "result": 3, "id": 3}


async def test_notifications_sent_while_handling_go_out_before_the_answer(conn: Conn) -> None:
    await conn.send({"jsonrpc": "2.0", "method": "flood", "params": {"count": 3}, "id": 1})
    ticks = [await conn.recv() for _ in range(3)]
    assert ticks == [
        {"jsonrpc": "2.0", "method": "tick", "params": {"i": i, "pad": ""}} for i in range(3)
    ]
    assert await conn.recv() == {"jsonrpc": "2.0", "result": 3, "id": 1}


async def test_notices_told_apart_reach_a_client_in_one_write_with_the_answer(
    conn: Conn, server: ApiServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A topic's notifications wait for the client's next message (NOTICE_DELAY, made
    long here so that only the answer can end the wait): five told in five loop passes
    and the request's answer reach the client in order, in one write, one wake-up."""
    monkeypatch.setattr(client_module, "NOTICE_DELAY", 3600.0)
    writes: list[bytes] = []  # what each write held
    await conn.send({"jsonrpc": "2.0", "method": "whoami", "id": 0})
    await conn.recv()  # the connection's client exists: count its writes
    for client in server.clients:
        real = client._write_staged

        def counted(transport: Any, messages: list[bytes], real: Any = real) -> None:
            writes.append(b"".join(messages))
            real(transport, messages)

        client._write_staged = counted  # type: ignore[method-assign]
    await conn.send({"jsonrpc": "2.0", "method": "tell", "params": {"count": 5}, "id": 1})
    ticks = [await conn.recv() for _ in range(5)]
    assert ticks == [{"jsonrpc": "2.0", "method": "tick", "params": {"i": i}} for i in range(5)]
    assert await conn.recv() == {"jsonrpc": "2.0", "result": 5, "id": 1}
    assert len(writes) == 1, writes


async def test_notices_with_no_answer_to_take_them_still_go_out_in_order(conn: Conn) -> None:
    """Told by a request without an id (no answer follows): the delay alone sends them."""
    await conn.send({"jsonrpc": "2.0", "method": "tell", "params": {"count": 3}})
    ticks = [await conn.recv() for _ in range(3)]
    assert ticks == [{"jsonrpc": "2.0", "method": "tick", "params": {"i": i}} for i in range(3)]


async def test_notices_still_waiting_go_out_before_the_server_drops_its_clients(
    harness: Harness, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The daemon stopping closes the server: what its clients were told last (a job
    interrupted by the stop) is written before they are dropped, not lost with the wait."""
    monkeypatch.setattr(client_module, "NOTICE_DELAY", 3600.0)
    async with serving(harness, tmp_path / "s") as server:
        assert server.path is not None
        conn = await Conn.open(server.path)
        try:
            await conn.send({"jsonrpc": "2.0", "method": "tell", "params": {"count": 3}})
            async with asyncio.timeout(TIMEOUT):
                await harness.told.wait()
            await server.close()
            ticks = [await conn.recv() for _ in range(3)]
            assert [t["params"]["i"] for t in ticks] == [0, 1, 2]
            assert await conn.closed_by_server()
        finally:
            await conn.close()


async def test_a_flood_that_fills_the_socket_arrives_whole_and_in_order(
    harness: Harness, tmp_path: Path
) -> None:
    """Written at the end of each loop pass while the socket keeps up, queued once it lags:
    either way, every message once, in the order sent, the answer last."""
    async with serving(harness, tmp_path / "s", queue_size=100_000) as server:
        assert server.path is not None
        conn = await Conn.open(server.path)
        try:
            count = 20_000  # 4 MB: far more than the socket's buffers hold
            params = {"count": count, "size": 200}
            await conn.send({"jsonrpc": "2.0", "method": "flood", "params": params, "id": 9})
            seen = [(await conn.recv())["params"]["i"] for _ in range(count)]
            assert seen == list(range(count))
            assert await conn.recv() == {"jsonrpc": "2.0", "result": count, "id": 9}
        finally:
            await conn.close()


# --- error codes --------------------------------------------------------------


@pytest.mark.parametrize(
    "line",
    [b"this is not json\n", b'{"jsonrpc": "2.0", "method": \n', b"\xff\xfe{}\n", b"NaN\n"],
    ids=["garbage", "truncated", "invalid-utf8", "nan"],
)
async def test_a_line_that_is_not_json_is_a_parse_error(conn: Conn, line: bytes) -> None:
    await conn.send_raw(line)
    answer = await conn.recv()
    assert answer["id"] is None
    assert answer["error"]["code"] == -32700
    assert answer["error"]["message"].startswith("parse error")


@pytest.mark.parametrize(
    ("request_", "id"),
    [
        (42, None),
        ("echo", None),
        ({"jsonrpc": "1.0", "method": "count", "id": 5}, 5),
        ({"method": "count", "id": "x"}, "x"),
        ({"jsonrpc": "2.0", "method": "count", "id": {"no": 1}}, None),
        ({"jsonrpc": "2.0", "method": "count", "id": True}, None),
        ({"jsonrpc": "2.0", "method": 12, "id": 6}, 6),
        ({"jsonrpc": "2.0", "method": "echo", "params": "hi", "id": 7}, 7),
        ({"jsonrpc": "2.0", "params": {}}, None),
    ],
    ids=[
        "number",
        "string",
        "wrong-version",
        "no-version",
        "object-id",
        "bool-id",
        "method-not-string",
        "params-scalar",
        "no-method-no-id",
    ],
)
async def test_a_malformed_request_is_an_invalid_request(
    conn: Conn, request_: Any, id: Any
) -> None:
    await conn.send(request_)
    answer = await conn.recv()
    assert answer["error"]["code"] == -32600
    assert answer["id"] == id


async def test_an_empty_batch_is_one_invalid_request_not_an_array(conn: Conn) -> None:
    await conn.send([])
    answer = await conn.recv()
    assert answer["error"] == {"code": -32600, "message": "invalid request: empty batch"}
    assert answer["id"] is None


async def test_an_unknown_method_is_method_not_found(conn: Conn) -> None:
    answer = await conn.call("machine.fly", id=3)
    assert answer["id"] == 3
    assert answer["error"] == {"code": -32601, "message": "method not found: machine.fly"}


@pytest.mark.parametrize(
    ("method", "params", "message"),
    [
        ("add", {"a": 1}, "invalid params: b: Field required"),
        ("add", {"a": 1, "b": "two"}, "invalid params: b: Input should be a valid integer"),
        ("echo", {"text": "x", "loud": True}, "invalid params: loud: Extra inputs are not"),
        ("echo", None, "invalid params: text: Field required"),
        ("echo", ["x"], "invalid params: params must be an object"),
        ("count", {"n": 1}, "invalid params: count takes no params"),
        ("count", [1], "invalid params: count takes no params"),
    ],
    ids=[
        "missing",
        "wrong-type",
        "extra-field",
        "absent",
        "by-position",
        "params-for-none",
        "array-for-none",
    ],
)
async def test_bad_params_are_invalid_params_naming_the_field(
    conn: Conn, method: str, params: Any, message: str
) -> None:
    answer = await conn.call(method, params, id=4)
    assert answer["id"] == 4
    assert answer["error"]["code"] == -32602
    assert answer["error"]["message"].startswith(message)


async def test_invalid_params_carry_pydantics_errors_as_data(conn: Conn) -> None:
    answer = await conn.call("add", {"b": "two"})
    assert answer["error"]["data"] == [
        {"loc": ["a"], "msg": "Field required", "type": "missing"},
        {
            "loc": ["b"],
            "msg": "Input should be a valid integer, unable to parse string as an integer",
            "type": "int_parsing",
        },
    ]


@pytest.mark.parametrize("params", [None, {}, []])
async def test_a_method_without_params_accepts_empty_or_absent_params(
    conn: Conn, params: Any
) -> None:
    request: dict[str, Any] = {"jsonrpc": "2.0", "method": "count", "id": 1, "params": params}
    await conn.send(request)
    assert (await conn.recv())["result"] == 1


async def test_a_crashing_handler_is_an_internal_error_logged_and_serving_goes_on(
    conn: Conn,
) -> None:
    with capture_logs() as logs:
        answer = await conn.call("boom", id=9)
    assert answer == {
        "jsonrpc": "2.0",
        "error": {"code": -32603, "message": "internal error"},
        "id": 9,
    }
    [entry] = [e for e in logs if e["event"] == "internal error"]
    assert entry["log_level"] == "error"
    assert entry["exc_info"] is True
    assert entry["method"] == "boom"
    assert (await conn.call("echo", {"text": "still here"}, id=10))["result"] == {
        "text": "still here"
    }


async def test_a_bug_past_the_dispatcher_is_an_internal_error_and_the_client_goes_on(
    conn: Conn, rpc_answer_fails_once: Callable[[], None]
) -> None:
    """rpc.answer answers everything itself; should it ever raise, the intake answers
    -32603 (id null: which request it was is rpc.answer's to know) and reads on."""
    rpc_answer_fails_once()
    with capture_logs() as logs:
        await conn.send({"jsonrpc": "2.0", "method": "echo", "params": {"text": "x"}, "id": 1})
        assert await conn.recv() == {
            "jsonrpc": "2.0",
            "error": {"code": -32603, "message": "internal error"},
            "id": None,
        }
    assert [e["log_level"] for e in logs if e["event"] == "dispatch failed"] == ["error"]
    assert (await conn.call("echo", {"text": "still here"}, id=2))["result"] == {
        "text": "still here"
    }


async def test_a_machine_error_passes_through_with_its_code_and_data(conn: Conn) -> None:
    assert (await conn.call("refuse", id=11))["error"] == {
        "code": 1003,
        "message": "machine busy",
        "data": {"supervisor": "operation"},
    }


# --- batches and pipelining ------------------------------------------------------


async def test_a_mixed_batch_is_answered_as_one_array_without_the_notifications(
    conn: Conn, harness: Harness
) -> None:
    await conn.send(
        [
            {"jsonrpc": "2.0", "method": "echo", "params": {"text": "a"}, "id": 1},
            {"jsonrpc": "1.0", "method": "echo", "id": 2},
            {"jsonrpc": "2.0", "method": "count"},
            {"jsonrpc": "2.0", "method": "add", "params": {"a": 1, "b": "x"}, "id": 3},
            {"jsonrpc": "2.0", "method": "nope", "id": 4},
            7,
        ]
    )
    answer = await conn.recv()
    assert isinstance(answer, list)
    assert len(answer) == 5
    assert harness.counted == 1  # the notification ran before the array was sent
    answers = by_id([a for a in answer if a["id"] is not None])
    assert answers[1]["result"] == {"text": "a"}
    assert answers[2]["error"]["code"] == -32600
    assert answers[3]["error"]["code"] == -32602
    assert answers[4]["error"]["code"] == -32601
    assert [a["error"]["code"] for a in answer if a["id"] is None] == [-32600]


async def test_a_batch_of_only_notifications_gets_no_answer(conn: Conn, harness: Harness) -> None:
    await conn.send([{"jsonrpc": "2.0", "method": "count"}, {"jsonrpc": "2.0", "method": "count"}])
    assert (await conn.call("count", id=5))["id"] == 5
    assert await conn.call("count", id=6) == {"jsonrpc": "2.0", "result": 4, "id": 6}


async def test_pipelined_requests_are_answered_as_they_complete(
    conn: Conn, harness: Harness
) -> None:
    await conn.send({"jsonrpc": "2.0", "method": "slow", "id": "slow"})
    async with asyncio.timeout(TIMEOUT):
        await harness.slow_started.wait()
    await conn.send({"jsonrpc": "2.0", "method": "echo", "params": {"text": "fast"}, "id": "fast"})
    assert (await conn.recv())["id"] == "fast"
    harness.release.set()
    assert await conn.recv() == {"jsonrpc": "2.0", "result": "slow done", "id": "slow"}


async def test_a_client_that_ends_its_side_still_gets_its_answers(conn: Conn) -> None:
    await conn.send({"jsonrpc": "2.0", "method": "add", "params": {"a": 1, "b": 1}, "id": 1})
    conn.writer.write_eof()
    assert (await conn.recv())["result"] == 2
    assert await conn.closed_by_server()


# --- limits -------------------------------------------------------------------


async def test_a_line_over_the_limit_is_refused_and_closed_while_others_are_served(
    server: ApiServer, conn: Conn
) -> None:
    assert server.path is not None
    other = await Conn.open(server.path)
    try:
        assert (await other.call("count", id=1))["result"] == 1
        text = "x" * (2 * MiB)
        await conn.send({"jsonrpc": "2.0", "method": "echo", "params": {"text": text}, "id": 1})
        assert await conn.recv() == {
            "jsonrpc": "2.0",
            "error": {"code": -32600, "message": "request line over 1048576 bytes"},
            "id": None,
        }
        assert await conn.closed_by_server()
        assert (await other.call("count", id=2))["result"] == 2
    finally:
        await other.close()


async def test_the_limit_counts_the_line_without_its_newline(
    harness: Harness, tmp_path: Path
) -> None:
    async with serving(harness, tmp_path / "s", max_line=64) as server:
        assert server.path is not None
        request = b'{"jsonrpc":"2.0","method":"count","id":1}'
        at_limit = request.ljust(64)
        conn = await Conn.open(server.path)
        try:
            await conn.send_raw(at_limit + b"\n")
            assert (await conn.recv())["result"] == 1
            await conn.send_raw(at_limit + b" \n")
            assert (await conn.recv())["error"] == {
                "code": -32600,
                "message": "request line over 64 bytes",
            }
            assert await conn.closed_by_server()
        finally:
            await conn.close()


async def test_a_client_that_stops_reading_is_disconnected_at_its_bound(
    server: ApiServer, harness: Harness
) -> None:
    assert server.path is not None
    deaf = await Conn.open(server.path)
    deaf.stop_reading()
    other = await Conn.open(server.path)
    try:
        await other.call("count")  # admitted and served before the flood
        with capture_logs() as logs:
            await deaf.send(
                {"jsonrpc": "2.0", "method": "flood", "params": {"count": 10**6, "size": 100}}
            )
            async with asyncio.timeout(TIMEOUT):
                await harness.disconnected.wait()
        [entry] = [e for e in logs if e["event"] == "api client not reading; disconnected"]
        assert entry["bound"] == 1000
        assert entry["pid"] == os.getpid()
        assert entry["uid"] == os.getuid()
        assert len(server.clients) == 1
        assert (await other.call("echo", {"text": "unaffected"}))["result"] == {
            "text": "unaffected"
        }
    finally:
        await deaf.close()
        await other.close()


async def test_a_write_that_does_not_drain_in_time_disconnects(
    harness: Harness, tmp_path: Path
) -> None:
    async with serving(harness, tmp_path / "s", write_timeout=0.2) as server:
        assert server.path is not None
        deaf = await Conn.open(server.path)
        deaf.stop_reading()
        try:
            with capture_logs() as logs:
                big = {
                    "count": 64,
                    "size": 64 * 1024,
                }  # 4 MiB in 64 messages: the queue never fills
                await deaf.send({"jsonrpc": "2.0", "method": "flood", "params": big})
                async with asyncio.timeout(TIMEOUT):
                    await harness.disconnected.wait()
            reasons = [e["reason"] for e in logs if e["event"] == "api client disconnected"]
            assert reasons == ["write did not drain within 0.2 s"]
            assert server.clients == []
        finally:
            await deaf.close()


async def test_a_batch_counts_each_request_against_the_clients_limit(
    harness: Harness, tmp_path: Path
) -> None:
    slow = {"jsonrpc": "2.0", "method": "slow"}
    async with serving(harness, tmp_path / "s", max_inflight=4) as server:
        assert server.path is not None
        conn = await Conn.open(server.path)
        try:
            for batch in range(3):  # nine requests on three lines; four may run at once
                await conn.send([{**slow, "id": f"{batch}.{i}"} for i in range(3)])
            async with asyncio.timeout(TIMEOUT):
                await harness.slow_started.wait()
            await asyncio.sleep(0.1)  # room for the second batch to start, were it let in
            assert harness.running == 3  # it waits: its three do not fit in the one left
            harness.release.set()
            answers = [await conn.recv() for _ in range(3)]
            assert sorted(a["id"] for batch in answers for a in batch) == [
                f"{b}.{i}" for b in range(3) for i in range(3)
            ]
            assert harness.peak == 3
        finally:
            await conn.close()


async def test_a_batch_larger_than_the_limit_is_refused_whole(
    harness: Harness, tmp_path: Path
) -> None:
    async with serving(harness, tmp_path / "s", max_inflight=4) as server:
        assert server.path is not None
        conn = await Conn.open(server.path)
        try:
            await conn.send([{"jsonrpc": "2.0", "method": "count", "id": i} for i in range(5)])
            assert await conn.recv() == {
                "jsonrpc": "2.0",
                "error": {"code": -32600, "message": "invalid request: batch over 4 requests"},
                "id": None,
            }
            await conn.send([{"jsonrpc": "2.0", "method": "count", "id": i} for i in range(4)])
            assert sorted(a["result"] for a in await conn.recv()) == [1, 2, 3, 4]
        finally:
            await conn.close()


async def test_past_max_clients_an_allowed_peer_is_told_the_daemon_is_full(
    harness: Harness, tmp_path: Path
) -> None:
    async with serving(harness, tmp_path / "s", max_clients=2) as server:
        assert server.path is not None
        first, second = await Conn.open(server.path), await Conn.open(server.path)
        try:
            assert (await first.call("count", id=1))["result"] == 1
            assert (await second.call("count", id=1))["result"] == 2
            with capture_logs() as logs:
                third = await Conn.open(server.path)
                await third.send({"jsonrpc": "2.0", "method": "count", "id": 1})
                assert await third.recv() == {
                    "jsonrpc": "2.0",
                    "error": {
                        "code": -32000,
                        "message": "daemon full: 2 clients connected; try again later",
                    },
                    "id": None,
                }
                assert await third.closed_by_server()
            [entry] = [e for e in logs if e["event"] == "api client refused: daemon full"]
            assert (entry["pid"], entry["uid"], entry["max_clients"]) == (
                os.getpid(),
                os.getuid(),
                2,
            )
            assert harness.counted == 2  # the refused request never ran
            assert server.admitted == 2
            assert (await first.call("count", id=2))["result"] == 3
            assert (await second.call("count", id=2))["result"] == 4
            await third.close()
        finally:
            await first.close()
            await second.close()


async def test_a_place_freed_by_a_client_that_left_is_taken_by_the_next(
    harness: Harness, tmp_path: Path
) -> None:
    async with serving(harness, tmp_path / "s", max_clients=1) as server:
        assert server.path is not None
        first = await Conn.open(server.path)
        await first.call("whoami")
        await first.close()
        async with asyncio.timeout(TIMEOUT):
            await harness.disconnected.wait()
            # It counts until its connection task has ended, a few loop passes after
            # its hooks ran; nothing signals that, so look (bounded by the timeout).
            while server.admitted:  # noqa: ASYNC110
                await asyncio.sleep(0.01)
        second = await Conn.open(server.path)
        try:
            assert (await second.call("count"))["result"] == 1
        finally:
            await second.close()


async def test_a_client_that_left_with_requests_running_still_counts(
    harness: Harness, tmp_path: Path
) -> None:
    async with serving(harness, tmp_path / "s", max_clients=1) as server:
        assert server.path is not None
        gone = await Conn.open(server.path)
        await gone.send({"jsonrpc": "2.0", "method": "slow", "id": 1})
        async with asyncio.timeout(TIMEOUT):
            await harness.slow_started.wait()
        await gone.close()
        newcomer = await Conn.open(server.path)
        try:
            assert (await newcomer.recv())["error"]["code"] == -32000
            harness.release.set()
        finally:
            await newcomer.close()


class _Gate:
    """An access policy that holds every peer at the door until opened."""

    def __init__(self) -> None:
        self.open = threading.Event()
        self.waiting = threading.Semaphore(0)

    def allows(self, peer: Any) -> bool:
        self.waiting.release()
        return self.open.wait(TIMEOUT)


@asynccontextmanager
async def _admissions_full(server: Any, gate: _Gate) -> AsyncIterator[list[Conn]]:
    """Two connections held at the door (the server's `max_clients` of 2): the next one
    to come is dropped before it is asked who it is."""
    assert server.path is not None
    held = [await Conn.open(server.path) for _ in range(2)]
    try:
        for _ in held:
            assert await asyncio.to_thread(gate.waiting.acquire, timeout=TIMEOUT)
        yield held
    finally:
        gate.open.set()
        for conn in held:
            await conn.close()


async def test_connections_waiting_for_admission_are_bounded_too(
    harness: Harness, tmp_path: Path
) -> None:
    gate = _Gate()
    async with (
        serving(harness, tmp_path / "s", max_clients=2, policy=gate) as server,
        _admissions_full(server, gate) as held,
    ):
        with capture_logs() as logs:
            dropped = await Conn.open(server.path)
            assert await dropped.closed_by_server()
        assert [e["event"] for e in logs] == ["api connection dropped: too many being admitted"]
        gate.open.set()
        for conn in held:
            assert (await conn.call("count"))["id"] == 1


async def test_a_flood_of_connections_past_the_bound_is_counted_not_logged_a_line_each(
    harness: Harness, tmp_path: Path
) -> None:
    """A local peer that opens connections in a loop makes the daemon drop each one; the
    log tells how many (every one) in a record a second at most, not a line each."""
    gate = _Gate()
    with capture_logs() as logs:
        async with (
            serving(harness, tmp_path / "s", max_clients=2, policy=gate) as server,
            _admissions_full(server, gate),
        ):
            started = time.monotonic()
            for _ in range(200):
                dropped = await Conn.open(server.path)
                assert await dropped.closed_by_server()
                await dropped.close()
            elapsed = time.monotonic() - started
    records = [e for e in logs if e["event"] == "api connection dropped: too many being admitted"]
    assert sum(e.get("repeats", 1) for e in records) == 200  # each one counted, at the close
    assert len(records) <= 2 + elapsed


async def test_a_half_sent_line_left_for_line_timeout_disconnects_only_that_client(
    harness: Harness, tmp_path: Path
) -> None:
    async with serving(harness, tmp_path / "s", line_timeout=0.2) as server:
        assert server.path is not None
        quiet = await Conn.open(server.path)
        await quiet.call("count", id=1)  # admitted; says nothing more from here on
        stalled = await Conn.open(server.path)
        try:
            await stalled.call("count", id=1)
            loop = asyncio.get_running_loop()
            with capture_logs() as logs:
                await stalled.send_raw(b'{"jsonrpc": "2.0", "method": "cou')
                sent = loop.time()
                assert await stalled.recv() == {
                    "jsonrpc": "2.0",
                    "error": {"code": -32600, "message": "request line not finished within 0.2 s"},
                    "id": None,
                }
                assert await stalled.closed_by_server()
            assert loop.time() - sent >= 0.2 - 0.002  # uvloop's timers count whole ms
            reasons = [e["reason"] for e in logs if e["event"] == "api client disconnected"]
            assert reasons == ["half a line for over 0.2 s"]
            # Quiet for longer than the timeout, but between lines: still served.
            assert (await quiet.call("count", id=2))["result"] == 3
            assert [c.id for c in server.clients] == [1]
        finally:
            await quiet.close()
            await stalled.close()


async def test_a_line_sent_in_pieces_within_the_timeout_is_one_request(
    harness: Harness, tmp_path: Path
) -> None:
    async with serving(harness, tmp_path / "s", line_timeout=5) as server:
        assert server.path is not None
        conn = await Conn.open(server.path)
        try:
            for piece in (b'{"jsonrpc": "2.0", ', b'"method": "count",', b' "id": 4}\n'):
                await conn.send_raw(piece)
            assert await conn.recv() == {"jsonrpc": "2.0", "result": 1, "id": 4}
        finally:
            await conn.close()


async def test_the_line_clock_stops_while_the_daemon_is_not_reading(
    harness: Harness, tmp_path: Path
) -> None:
    """At its limit of requests in flight the client is not read: that is not its stall."""
    async with serving(harness, tmp_path / "s", max_inflight=1, line_timeout=0.2) as server:
        assert server.path is not None
        conn = await Conn.open(server.path)
        try:
            await conn.send({"jsonrpc": "2.0", "method": "slow", "id": "slow"})
            async with asyncio.timeout(TIMEOUT):
                await harness.slow_started.wait()
            await conn.send_raw(b'{"jsonrpc": "2.0", "method": "count", "id": 1}\n{"jsonrpc"')
            await asyncio.sleep(0.4)  # twice the line timeout, all of it spent waiting on us
            harness.release.set()
            assert (await conn.recv())["id"] == "slow"
            assert (await conn.recv())["id"] == 1
            await conn.send_raw(b': "2.0", "method": "count", "id": 2}\n')
            assert (await conn.recv())["result"] == 2
        finally:
            await conn.close()


# --- the socket file and its peers -------------------------------------------


async def test_the_socket_file_is_0600_without_a_group(server: ApiServer) -> None:
    assert server.path is not None
    st = os.stat(server.path)
    assert stat.S_ISSOCK(st.st_mode)
    assert stat.S_IMODE(st.st_mode) == 0o600


async def test_the_socket_gets_the_configured_group_and_the_umask_is_restored(
    harness: Harness, tmp_path: Path
) -> None:
    umask = os.umask(0o022)
    try:
        async with serving(harness, tmp_path / "s", socket_gid=os.getgid()) as server:
            assert server.path is not None
            assert os.stat(server.path).st_gid == os.getgid()
            assert stat.S_IMODE(os.stat(server.path).st_mode) == 0o660
            assert os.umask(0o022) == 0o022
    finally:
        os.umask(umask)


@pytest.mark.parametrize("gid", [None, os.getgid()], ids=["no-group", "group"])
async def test_the_socket_is_born_0600_whatever_the_umask_it_inherits(
    harness: Harness, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, gid: int | None
) -> None:
    """Seen at the first thing done to the file after bind(): it already exists, at 0600."""
    real_chown, real_chmod = os.chown, os.chmod
    seen: list[tuple[str, int, int]] = []  # (call, the file's mode then, the umask then)

    def look(call: str, path: Any) -> None:
        umask = os.umask(0)
        os.umask(umask)
        seen.append((call, stat.S_IMODE(os.lstat(path).st_mode), umask))

    def chown(path: Any, *args: Any, **kwargs: Any) -> None:
        look("chown", path)
        real_chown(path, *args, **kwargs)

    def chmod(path: Any, *args: Any, **kwargs: Any) -> None:
        look("chmod", path)
        real_chmod(path, *args, **kwargs)

    monkeypatch.setattr(os, "chown", chown)
    monkeypatch.setattr(os, "chmod", chmod)
    umask = os.umask(0)  # the loosest a parent could hand down
    try:
        async with serving(harness, tmp_path / "s", socket_gid=gid) as server:
            assert server.path is not None
            final = stat.S_IMODE(os.stat(server.path).st_mode)
    finally:
        os.umask(umask)
    expected = [("chmod", 0o600, 0)] if gid is None else [("chown", 0o600, 0), ("chmod", 0o600, 0)]
    assert seen == expected
    assert final == (0o600 if gid is None else 0o660)


async def test_a_regular_file_at_the_path_is_not_deleted(harness: Harness, tmp_path: Path) -> None:
    path = tmp_path / "precious"
    path.write_text("keep me")
    server = ApiServer(harness.methods)
    with pytest.raises(SocketPathError, match="exists and is not a socket; refusing to remove"):
        await server.start(path)
    assert path.read_text() == "keep me"
    await server.close()
    assert path.read_text() == "keep me"


async def test_a_stale_socket_is_replaced(harness: Harness, tmp_path: Path) -> None:
    path = tmp_path / "s"
    leftover = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    leftover.bind(str(path))
    leftover.close()  # the file stays, nobody listens: what a crashed daemon leaves
    async with serving(harness, path):
        conn = await Conn.open(path)
        assert (await conn.call("count"))["result"] == 1
        await conn.close()


async def test_a_socket_someone_listens_on_is_not_taken_over(
    server: ApiServer, harness: Harness
) -> None:
    assert server.path is not None
    second = ApiServer(harness.methods)
    with pytest.raises(SocketPathError, match="in use"):
        await second.start(server.path)
    await second.close()
    conn = await Conn.open(server.path)
    assert (await conn.call("count"))["result"] == 1
    await conn.close()


async def test_a_planted_symlink_is_refused_and_left_alone(
    harness: Harness, tmp_path: Path
) -> None:
    target = tmp_path / "elsewhere"
    path = tmp_path / "s"
    path.symlink_to(target)
    server = ApiServer(harness.methods)
    with pytest.raises(SocketPathError, match=r"s is a symbolic link; refusing to follow"):
        await server.start(path)
    await server.close()
    assert path.is_symlink() and os.readlink(path) == str(target)
    assert not target.exists()


async def test_a_symlink_to_a_stale_socket_is_refused_not_followed(
    harness: Harness, tmp_path: Path
) -> None:
    stale = tmp_path / "stale"
    leftover = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    leftover.bind(str(stale))
    leftover.close()
    path = tmp_path / "s"
    path.symlink_to(stale)
    server = ApiServer(harness.methods)
    with pytest.raises(SocketPathError, match="symbolic link"):
        await server.start(path)
    assert path.is_symlink() and stale.exists()


@pytest.mark.parametrize(
    ("mode", "who"), [(0o770, "its group"), (0o707, "others"), (0o777, "others")]
)
async def test_a_directory_others_may_write_without_the_sticky_bit_is_refused(
    harness: Harness, tmp_path: Path, mode: int, who: str
) -> None:
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(mode)
    server = ApiServer(harness.methods)
    with pytest.raises(SocketPathError) as refused:
        await server.start(shared / "s")
    assert str(refused.value) == (
        f"the socket's directory {shared} is writable by {who} (mode 0{mode:o}) without the"
        f" sticky bit, so they could replace the socket; use a directory only the daemon's"
        f" user can write (chmod go-w {shared})"
    )
    assert os.listdir(shared) == []


async def test_a_sticky_directory_like_tmp_is_fine(harness: Harness, tmp_path: Path) -> None:
    shared = tmp_path / "tmp"
    shared.mkdir()
    shared.chmod(0o1777)
    async with serving(harness, shared / "s"):
        conn = await Conn.open(shared / "s")
        assert (await conn.call("count"))["result"] == 1
        await conn.close()


@pytest.mark.skipif(os.geteuid() != 0, reason="giving a directory away takes root")
async def test_a_directory_another_user_owns_is_refused(harness: Harness, tmp_path: Path) -> None:
    theirs = tmp_path / "theirs"
    theirs.mkdir(mode=0o755)
    os.chown(theirs, 4321, -1)
    server = ApiServer(harness.methods)
    with pytest.raises(SocketPathError, match="belongs to uid 4321, who could replace"):
        await server.start(theirs / "s")


async def test_a_missing_directory_is_named(harness: Harness, tmp_path: Path) -> None:
    server = ApiServer(harness.methods)
    with pytest.raises(SocketPathError, match=f"directory {tmp_path}/nope does not exist"):
        await server.start(tmp_path / "nope" / "s")


async def test_a_path_too_long_for_a_socket_is_one_clear_error(
    harness: Harness, tmp_path: Path
) -> None:
    server = ApiServer(harness.methods)
    with pytest.raises(
        SocketPathError, match=r"cannot create the socket .*: AF_UNIX path too long"
    ):
        await server.start(tmp_path / ("x" * 120))


async def test_a_peer_the_policy_denies_is_closed_without_an_answer(
    harness: Harness, tmp_path: Path
) -> None:
    nobody = AccessPolicy(allowed_uids=set(), allowed_gids=set())
    with capture_logs() as logs:
        async with serving(harness, tmp_path / "s", policy=nobody) as server:
            assert server.path is not None
            conn = await Conn.open(server.path)
            async with asyncio.timeout(TIMEOUT):
                data = await conn.reader.read()
            assert data == b""
            assert server.clients == []
            await conn.close()
    [entry] = [e for e in logs if e["event"] == "api client denied"]
    assert entry["log_level"] == "warning"
    assert (entry["pid"], entry["uid"], entry["gid"]) == (os.getpid(), os.getuid(), os.getgid())
    assert harness.counted == 0


async def test_close_drops_clients_runs_their_hooks_and_removes_the_socket_file(
    server: ApiServer, harness: Harness
) -> None:
    assert server.path is not None
    path = Path(server.path)
    conn = await Conn.open(path)
    await conn.call("whoami")
    await conn.send({"jsonrpc": "2.0", "method": "slow", "id": 2})
    async with asyncio.timeout(TIMEOUT):
        await harness.slow_started.wait()
    await server.close()
    assert path.name not in os.listdir(path.parent)
    assert harness.disconnected.is_set()
    assert server.clients == []
    assert await conn.closed_by_server()
    await conn.close()


async def test_a_realtime_request_alone_is_answered_with_its_id(
    conn: Conn, harness: Harness
) -> None:
    assert await conn.call("machine.mark", id=41) == {
        "jsonrpc": "2.0",
        "result": "marked",
        "id": 41,
    }
    assert harness.order == ["mark"]


async def test_a_realtime_request_never_overtakes_what_the_client_sent_before(
    conn: Conn, harness: Harness
) -> None:
    first = {"jsonrpc": "2.0", "method": "note", "id": 1}
    second = {"jsonrpc": "2.0", "method": "machine.mark", "id": 2}
    await conn.send_raw(json.dumps(first).encode() + b"\n" + json.dumps(second).encode() + b"\n")
    answers = {(await conn.recv())["id"], (await conn.recv())["id"]}
    assert answers == {1, 2}
    assert harness.order == ["note", "mark"]


async def test_a_realtime_name_inside_a_broken_line_runs_nothing(
    conn: Conn, harness: Harness
) -> None:
    await conn.send_raw(b'{"jsonrpc":"2.0","id":3,"method":"machine.mark"\n')
    assert (await conn.recv())["error"]["code"] == -32700
    assert harness.order == []
