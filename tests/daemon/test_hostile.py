"""Hostile lines and values (issue 11 item 5), through the real socket against the simulated board.

Each refusal is -32602 with a message that says why, and nothing reaches the
board: after the refused request a harmless query is answered, and every
line the board received in between is one of the daemon's own status
requests. Refused operations leave no job row either.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Awaitable
from typing import Any

import pytest

from tests.daemon.conftest import Rpc, RpcFailure, Running
from tests.daemon.test_api import fails

pytestmark = pytest.mark.asyncio

OWN_POLL = b'{"sr":null}'  # the daemon's status request: the only other line allowed
SENTINEL, SENTINEL_SENT = "{fv:n}", b'{"fv":null}'


async def refused(hostd: Running, rpc: Rpc, call: Awaitable[Any]) -> RpcFailure:
    """Await `call`, which must fail with -32602 without writing anything to the board."""
    sim = hostd.daemon.sims["sim1"]
    since = time.monotonic()
    jobs_before = len(await rpc.call("job.list", machine="sim1"))
    with pytest.raises(RpcFailure) as err:
        await call
    assert err.value.code == -32602, err.value
    assert err.value.message
    # Answered, so the board has read everything written before it.
    await rpc.call("machine.send", machine="sim1", line=SENTINEL)
    received = [r.data for r in sim.received if r.t >= since]
    assert SENTINEL_SENT in received, received
    assert set(received) <= {OWN_POLL, SENTINEL_SENT}, f"the board received {received}"
    assert len(await rpc.call("job.list", machine="sim1")) == jobs_before
    return err.value


async def raw_call(hostd: Running, request: str) -> dict[str, Any]:
    """One request written as raw text (for 1e999, which json.dumps cannot write)."""
    reader, writer = await asyncio.open_unix_connection(hostd.socket)
    try:
        writer.write(request.encode() + b"\n")
        async with asyncio.timeout(10):
            answer: dict[str, Any] = json.loads(await reader.readline())
        return answer
    finally:
        writer.close()


def send(rpc: Rpc, line: str) -> Awaitable[Any]:
    return rpc.call("machine.send", machine="sim1", line=line)


# -- duplicate keys and lines the host cannot read -----------------------------


async def test_a_json_line_with_a_duplicate_key_is_refused_unsent(hostd: Running, rpc: Rpc) -> None:
    err = await refused(hostd, rpc, send(rpc, '{"gc":"G0 X100","clear":n,"gc":n}'))
    assert err.data == {"refusal": "duplicate-key"} and "'gc'" in err.message
    err = await refused(hostd, rpc, send(rpc, '{gc:"G0 X100",GC:n}'))
    assert err.data == {"refusal": "duplicate-key"}
    assert hostd.daemon.sims["sim1"].position["x"] == 0


@pytest.mark.parametrize(
    "line", ["{not json", "{xvm:1} G0 X100", "{x:{vm:1},am:n}", '{xvm:"a\\"b"}', "$xvm = 100"]
)
async def test_a_line_the_host_cannot_read_as_the_board_does_is_refused_unsent(
    hostd: Running, rpc: Rpc, line: str
) -> None:
    # Before, a '{' line the daemon could not parse was classified ACTION and sent.
    err = await refused(hostd, rpc, send(rpc, line))
    assert err.data == {"refusal": "unreadable"}


# -- numbers -------------------------------------------------------------------


@pytest.mark.parametrize(
    "line", ["G0 X1e300", "G0 X99999999999", "G0 X1 000", '{gc:"G0 X1e300"}', "{xvm:1e300}"]
)
async def test_gcode_and_json_numbers_the_board_would_misread_are_refused_unsent(
    hostd: Running, rpc: Rpc, line: str
) -> None:
    err = await refused(hostd, rpc, send(rpc, line))
    assert err.data == {"refusal": "bad-number"}


async def test_an_active_comment_is_refused_unsent(hostd: Running, rpc: Rpc) -> None:
    err = await refused(hostd, rpc, send(rpc, "G0 X1 ({flash:t})"))
    assert err.data == {"refusal": "active-comment"}


@pytest.mark.parametrize(
    ("axes", "feed"),
    [
        ({"x": 1e300}, 600),
        ({"x": 100000.5}, 600),
        ({"x": 1}, 1e300),
        ({"x": 1}, 0),
        ({"x": 1}, 1000001),
        ({"x": "1"}, 600),  # a string is not a number
        ({"x": True}, 600),
    ],
)
async def test_a_jog_with_an_absurd_value_is_refused_before_anything_moves(
    hostd: Running, rpc: Rpc, axes: dict[str, Any], feed: Any
) -> None:
    await refused(hostd, rpc, rpc.call("machine.jog", machine="sim1", axes=axes, feed=feed))


async def test_an_infinite_jog_is_refused(hostd: Running, rpc: Rpc) -> None:
    # 1e999 is valid JSON that Python reads as infinity.
    answer = await raw_call(
        hostd,
        '{"jsonrpc":"2.0","id":1,"method":"machine.jog",'
        '"params":{"machine":"sim1","axes":{"x":1e999},"feed":600}}',
    )
    assert answer["error"]["code"] == -32602
    answer = await raw_call(
        hostd,
        '{"jsonrpc":"2.0","id":2,"method":"machine.send",'
        '"params":{"machine":"sim1","line":"G0","timeout":1e999}}',
    )
    assert answer["error"]["code"] == -32602


async def test_a_jog_within_bounds_is_written_with_fixed_decimals(hostd: Running, rpc: Rpc) -> None:
    await rpc.call("subscribe", topics=["job"], machine="sim1")
    job = await rpc.call("machine.jog", machine="sim1", axes={"x": 0.12345}, feed=1234.5678)
    await rpc.notification(
        lambda n: (
            n["method"] == "job"
            and n["params"]["job"]["id"] == job["job"]
            and n["params"]["job"]["state"] == "completed"
        )
    )
    lines = [r.data for r in hostd.daemon.sims["sim1"].received if r.kind == "line"]
    assert b"G91 G1 X0.1235 F1234.568" in lines


@pytest.mark.parametrize(
    ("method", "params"),
    [
        ("job.get", {"job": 10**30}),
        ("job.get", {"job": 0}),
        ("job.get", {"job": 1.0}),
        ("job.list", {"limit": "5"}),
        ("job.list", {"limit": 10**6}),
        ("unsubscribe", {"subscription": 10**30}),
        ("machine.send", {"machine": "sim1", "line": "G0", "timeout": 1e300}),
        ("machine.send", {"machine": "sim1", "line": "G0", "timeout": True}),
        ("job.start", {"machine": "sim1", "file": "a.gcode", "start_line": 10**30}),
    ],
)
async def test_every_numeric_parameter_is_bounded(
    hostd: Running, rpc: Rpc, method: str, params: dict[str, Any]
) -> None:
    await refused(hostd, rpc, rpc.call(method, **params))


# -- settings ------------------------------------------------------------------


@pytest.mark.parametrize(
    "key", ["gc", "gc2", "ej", "jv", "sv", "si", "qv", "tv", "defa", "boot", "sr", "clear", "GC"]
)
async def test_settings_set_refuses_names_that_are_not_settings(
    hostd: Running, rpc: Rpc, key: str
) -> None:
    err = await refused(
        hostd, rpc, rpc.call("settings.set", machine="sim1", values={key: "G0X100"})
    )
    assert repr(key.lower()) in err.message


@pytest.mark.parametrize(
    "values", [{"xvm": 1e300}, {"xvm": 10**12}, {"xvm": "a b"}, {"xvm": ""}, {"xvm": 1, "XVM": 2}]
)
async def test_settings_set_refuses_values_the_board_would_misread(
    hostd: Running, rpc: Rpc, values: dict[str, Any]
) -> None:
    await refused(hostd, rpc, rpc.call("settings.set", machine="sim1", values=values))


async def test_settings_get_refuses_names_whose_get_acts(hostd: Running, rpc: Rpc) -> None:
    err = await refused(hostd, rpc, rpc.call("settings.get", machine="sim1", keys=["clear"]))
    assert "machine.clear" in err.message
    await refused(hostd, rpc, rpc.call("settings.get", machine="sim1", keys=["xvm", "alarm"]))


async def test_machine_send_may_not_set_what_the_daemon_owns(hostd: Running, rpc: Rpc) -> None:
    err = await refused(hostd, rpc, send(rpc, "{jv:0}"))
    assert err.data == {"refusal": "reserved-key"}
    await refused(hostd, rpc, send(rpc, "$ej=0"))
    assert (await send(rpc, "{jv:n}"))["r"]["jv"] == 4  # reading it is fine


async def test_settings_set_writes_numbers_plainly(hostd: Running, rpc: Rpc) -> None:
    assert await rpc.call("settings.set", machine="sim1", values={"XVM": 12000.5}) == {
        "xvm": 12000.5
    }
    lines = [r.data for r in hostd.daemon.sims["sim1"].received if r.kind == "line"]
    assert b'{"xvm":12000.5}' in lines


# -- job files -------------------------------------------------------------------


async def test_a_job_line_the_board_would_misread_fails_the_job_unsent(
    hostd: Running, rpc: Rpc
) -> None:
    await rpc.call("file.upload", name="bad.gcode", data="G0 X1\nG0 X1e300\nG0 X2\n")
    await rpc.call("subscribe", topics=["job"], machine="sim1")
    refused = await fails(1008, rpc.call("job.start", machine="sim1", file="bad.gcode"))
    assert refused.data["problems"][0]["line"] == 2  # refused before anything moved
    job = await rpc.call("job.start", machine="sim1", file="bad.gcode", force=True)
    note = await rpc.notification(
        lambda n: (
            n["method"] == "job"
            and n["params"]["job"]["id"] == job["job"]
            and n["params"]["job"]["state"] not in ("running", "paused")
        )
    )
    ended = note["params"]["job"]
    assert ended["state"] == "failed"
    assert ended["error"]["code"] == -32602 and "line 2" in ended["error"]["message"]
    lines = [r.data for r in hostd.daemon.sims["sim1"].received if r.kind == "line"]
    assert b"G0 X1e300" not in lines and b"G0 X2" not in lines
