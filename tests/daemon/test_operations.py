"""The operator's day, first slice: home, zero, go to zero, spindle and overrides on both dialects.

A g2core board and a grbl laser, simulated on real ptys, reached through the
real Unix socket. What a user would notice: the machine is homed after home,
the position reads zero after zero, the tool is back at zero after goto_zero,
the lines on the wire are the firmware's own, and what is refused says why.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio

from hostd.sim.grbl.controller import GrblSimController
from tests.daemon.conftest import Rpc, RpcFailure, Running, running_daemon
from tests.daemon.test_api import fails, job_end

pytestmark = pytest.mark.asyncio

G2, GRBL = "sim1", "sim2"
MACHINES = (G2, GRBL)


@pytest_asyncio.fixture
async def both(tmp_path: Path) -> AsyncIterator[tuple[Running, Rpc]]:
    async with running_daemon(tmp_path, machines=2, per_machine=[{}, {"dialect": "grbl"}]) as d:
        client = await d.client()
        await client.call("subscribe", topics=["job"])
        for machine in MACHINES:
            await d.idle(client, machine)
        # The grbl laser gets homing switches, as its owner would set them ($22=1).
        await client.call("settings.set", machine=GRBL, values={"22": 1})
        await d.idle(client, GRBL)
        yield d, client
        await client.close()


def lines_sent(hostd: Running, machine: str) -> list[bytes]:
    """The lines the board read (the grbl sim keeps raw chunks: split into lines)."""
    sim = hostd.daemon.sims[machine]
    if machine == GRBL:
        realtime = b"?!~\x18" + bytes(range(0x80, 0x100))  # between lines, never in one
        data = b"".join(r.data for r in sim.received).translate(None, realtime)
        return [line.strip() for line in data.split(b"\n") if line.strip()]
    return [r.data.strip() for r in sim.received if r.kind == "line"]


async def jog_to(hostd: Running, rpc: Rpc, machine: str, axes: dict[str, float]) -> None:
    job = await rpc.call("machine.jog", machine=machine, axes=axes, feed=3000)
    await job_end(rpc, job["job"])
    await hostd.idle(rpc, machine)


@pytest.mark.parametrize("machine", MACHINES)
async def test_home_answers_once_the_cycle_is_done_and_the_machine_is_homed(
    both: tuple[Running, Rpc], machine: str
) -> None:
    hostd, rpc = both
    await jog_to(hostd, rpc, machine, {"x": 5, "y": 3})
    assert await rpc.call("machine.home", machine=machine) == {}
    snap = await rpc.call("machine.status", machine=machine)
    assert snap["homed"] is True
    assert snap["state"]["name"] != "HOMING"
    want = b"$H" if machine == GRBL else b"G28.2 X0 Y0 Z0"
    assert want in lines_sent(hostd, machine)


async def test_g2core_homes_only_the_axes_asked(both: tuple[Running, Rpc]) -> None:
    hostd, rpc = both
    await jog_to(hostd, rpc, G2, {"x": 4})
    assert await rpc.call("machine.home", machine=G2, axes=["z", "x"]) == {}
    assert b"G28.2 Z0 X0" in lines_sent(hostd, G2)


async def test_grbl_refuses_homing_some_axes_and_sends_nothing(both: tuple[Running, Rpc]) -> None:
    hostd, rpc = both
    err = await fails(-32602, rpc.call("machine.home", machine=GRBL, axes=["x"]))
    assert "$H" in err.message
    assert not any(line.startswith(b"$H") for line in lines_sent(hostd, GRBL))


@pytest.mark.parametrize(
    "params",
    [{"axes": ["q"]}, {"axes": []}, {"axes": ["x", "x"]}, {"axes": "xyz"}],
)
async def test_home_refuses_bad_axes(both: tuple[Running, Rpc], params: dict[str, Any]) -> None:
    _, rpc = both
    await fails(-32602, rpc.call("machine.home", machine=G2, **params))


@pytest.mark.parametrize("machine", MACHINES)
async def test_home_is_refused_while_a_jog_runs(both: tuple[Running, Rpc], machine: str) -> None:
    hostd, rpc = both
    job = await rpc.call("machine.jog", machine=machine, axes={"x": 200}, feed=100)
    err = await fails(1003, rpc.call("machine.home", machine=machine))
    assert "idle" in err.message
    await fails(1003, rpc.call("machine.goto_zero", machine=machine))
    await fails(1003, rpc.call("machine.spindle", machine=machine, state="cw", speed=100))
    await rpc.call("machine.jog_stop", machine=machine)
    await job_end(rpc, job["job"])
    assert not any(line.startswith((b"$H", b"G28.2", b"M3")) for line in lines_sent(hostd, machine))


async def test_grbl_homes_out_of_an_alarm_as_its_firmware_allows(
    both: tuple[Running, Rpc],
) -> None:
    hostd, rpc = both
    await rpc.call("settings.set", machine=GRBL, values={"21": 1})  # hard limits on
    await hostd.idle(rpc, GRBL)
    await rpc.call("subscribe", topics=["status"], machine=GRBL)
    sim = hostd.daemon.sims[GRBL]
    assert isinstance(sim, GrblSimController)
    sim.limit_switch("x")  # a hard limit: ALARM:1
    await rpc.notification(
        lambda n: n["method"] == "status" and n["params"]["snapshot"]["state"]["name"] == "ALARM"
    )
    sim.limit_switch("x", active=False)
    # A hard limit reads nothing until a reset; after it the board stays in ALARM,
    # and `$H` or `$X` unlock it (gnea/grbl protocol.c, system.c).
    await rpc.call("machine.reset", machine=GRBL)
    snap = await rpc.call("machine.status", machine=GRBL)
    assert snap["state"]["name"] == "ALARM"
    await fails(204, rpc.call("machine.spindle", machine=GRBL, state="cw", speed=10))
    assert await rpc.call("machine.home", machine=GRBL) == {}
    snap = await rpc.call("machine.status", machine=GRBL)
    assert snap["homed"] is True and snap["state"]["name"] != "ALARM"


async def test_g2core_refuses_homing_in_an_alarm(both: tuple[Running, Rpc]) -> None:
    hostd, rpc = both
    await rpc.call("subscribe", topics=["status"], machine=G2)
    await rpc.call("machine.alarm", machine=G2)
    await rpc.notification(
        lambda n: n["method"] == "status" and n["params"]["snapshot"]["state"]["name"] == "ALARM"
    )
    await fails(204, rpc.call("machine.home", machine=G2))
    assert b"G28.2 X0 Y0 Z0" not in lines_sent(hostd, G2)


@pytest.mark.parametrize("machine", MACHINES)
async def test_zero_then_goto_zero_brings_the_tool_back(
    both: tuple[Running, Rpc], machine: str
) -> None:
    hostd, rpc = both
    await jog_to(hostd, rpc, machine, {"x": 7, "y": 4})
    snap = await rpc.call("machine.zero", machine=machine, axes={"x": 0, "y": 1.5})
    assert snap["id"] == machine
    # The answer is the snapshot after a report that has the new offset in it (grbl: a
    # `?` asked after the G10's ok), not the one from before the zero.
    assert snap["work_position"]["x"] == pytest.approx(0, abs=1e-3)
    assert snap["work_position"]["y"] == pytest.approx(1.5, abs=1e-3)
    assert snap["machine_position"]["x"] == pytest.approx(7, abs=1e-3)
    assert any(line.startswith(b"G10 L20 P") for line in lines_sent(hostd, machine))
    await rpc.call("subscribe", topics=["status"], machine=machine)
    status = await rpc.notification(
        lambda n: (
            n["method"] == "status"
            and n["params"]["snapshot"]["work_position"].get("x") == pytest.approx(0, abs=1e-3)
        )
    )
    assert status["params"]["snapshot"]["work_position"]["y"] == pytest.approx(1.5, abs=1e-3)
    await jog_to(hostd, rpc, machine, {"x": 3, "y": -2})
    assert await rpc.call("machine.goto_zero", machine=machine, axes=["x", "y"]) == {}
    snap = await rpc.call("machine.status", machine=machine)
    assert snap["work_position"]["x"] == pytest.approx(0, abs=1e-3)
    assert snap["work_position"]["y"] == pytest.approx(0, abs=1e-3)
    assert snap["machine_position"]["x"] == pytest.approx(7, abs=1e-3)


async def test_goto_zero_raises_z_to_the_safe_height_first(tmp_path: Path) -> None:
    async with running_daemon(tmp_path, safe_z=-1.0) as hostd:
        rpc = await hostd.client()
        await rpc.call("subscribe", topics=["job"])
        await hostd.idle(rpc)
        await jog_to(hostd, rpc, G2, {"z": -5})  # below the safe height
        assert await rpc.call("machine.goto_zero", machine=G2) == {}
        sent = lines_sent(hostd, G2)
        moves = [line for line in sent if line.startswith((b"G53", b"G90 G0"))]
        assert moves[-3:] == [b"G53 G0 Z-1", b"G90 G0 X0 Y0", b"G90 G0 Z0"]
        # X alone: Z still rises first, and stays up.
        await jog_to(hostd, rpc, G2, {"z": -5})
        assert await rpc.call("machine.goto_zero", machine=G2, axes=["x"]) == {}
        sent = lines_sent(hostd, G2)
        moves = [line for line in sent if line.startswith((b"G53", b"G90 G0"))]
        assert moves[-2:] == [b"G53 G0 Z-1", b"G90 G0 X0"]
        await rpc.close()


@pytest.mark.parametrize("machine", MACHINES)
async def test_the_travel_check_reads_the_positions_in_their_own_units_under_g20(
    both: tuple[Running, Rpc], machine: str
) -> None:
    """A board left in G20 by an inch program: g2core still reports its machine position
    in mm (only `pos` follows G20), grbl both in mm (only `$13` changes them). The work
    offset is their difference in mm; scaling both by 25.4, as before, put a program
    that fits 2.5 m away here (a false refusal), and can put one that does not inside."""
    hostd, rpc = both
    assert await rpc.call("machine.home", machine=machine) == {}
    inside = 100.0 if machine == G2 else -100.0  # g2core's travel 0..300, grbl's -200..0
    await jog_to(hostd, rpc, machine, {"x": inside - rpc_x(await status(rpc, machine))})
    await rpc.call("machine.zero", machine=machine, axes={"x": 0})
    await rpc.call("subscribe", topics=["status"], machine=machine)
    await rpc.call("machine.send", machine=machine, line="G20")
    if machine == GRBL:
        await rpc.call("machine.send", machine=machine, line="$G")  # grbl says it in `$G`
    await rpc.notification(
        lambda n: n["method"] == "status" and n["params"]["snapshot"]["units"] == "in"
    )
    await rpc.call("file.upload", name="fits.nc", data="G20 G90\nG0 X1\n")  # 25.4 mm over
    await rpc.call("file.upload", name="far.nc", data="G20 G90\nG0 X-5\n")  # 127 mm under
    fits = await rpc.call("file.analyze", file="fits.nc", machine=machine)
    assert fits["travel_checked"] and fits["beyond_travel"] == [], fits["beyond_travel"]
    far = await rpc.call("file.analyze", file="far.nc", machine=machine)
    assert [text[0] for text in far["beyond_travel"]] == ["X"]
    assert f"{inside - 127:.3f}" in far["beyond_travel"][0]  # machine mm, as it would go


async def status(rpc: Rpc, machine: str) -> dict[str, Any]:
    snapshot: dict[str, Any] = await rpc.call("machine.status", machine=machine)
    return snapshot


def rpc_x(snapshot: dict[str, Any]) -> float:
    return float(snapshot["machine_position"]["x"])


@pytest.mark.parametrize("axes", [{}, {"q": 1}, {"x": "1"}, {"x": 1e12}])
async def test_zero_refuses_bad_axes(both: tuple[Running, Rpc], axes: dict[str, Any]) -> None:
    hostd, rpc = both
    await fails(-32602, rpc.call("machine.zero", machine=G2, axes=axes))
    assert not any(line.startswith(b"G10") for line in lines_sent(hostd, G2))


@pytest.mark.parametrize("machine", MACHINES)
async def test_spindle_on_and_off(both: tuple[Running, Rpc], machine: str) -> None:
    hostd, rpc = both
    assert await rpc.call("machine.spindle", machine=machine, state="cw", speed=800) == {}
    assert await rpc.call("machine.spindle", machine=machine, state="ccw") == {}
    assert await rpc.call("machine.spindle", machine=machine, state="off") == {}
    sent = lines_sent(hostd, machine)
    assert [x for x in sent if x[:2] in (b"M3", b"M4", b"M5")] == [b"M3 S800", b"M4", b"M5"]
    await fails(-32602, rpc.call("machine.spindle", machine=machine, state="on"))
    await fails(-32602, rpc.call("machine.spindle", machine=machine, state="cw", speed=-1))


async def test_grbl_reports_its_spindle_in_the_snapshot(both: tuple[Running, Rpc]) -> None:
    _, rpc = both
    await rpc.call("subscribe", topics=["status"], machine=GRBL)
    await rpc.call("machine.spindle", machine=GRBL, state="ccw", speed=300)
    await rpc.notification(
        lambda n: (
            n["method"] == "status"
            and (n["params"]["snapshot"]["spindle"] or {}).get("state") == "ccw"
        )
    )
    await rpc.call("machine.spindle", machine=GRBL, state="off")
    await rpc.notification(
        lambda n: (
            n["method"] == "status"
            and (n["params"]["snapshot"]["spindle"] or {}).get("state") == "off"
        )
    )


async def test_grbl_override_answers_the_overrides_in_force(both: tuple[Running, Rpc]) -> None:
    _, rpc = both
    got = await rpc.call("machine.override", machine=GRBL, feed=120, rapid=50, spindle=80)
    assert got == {"feed": 120, "spindle": 80, "rapid": 50}
    got = await rpc.call("machine.override", machine=GRBL, feed=90)
    assert got == {"feed": 90, "spindle": 80, "rapid": 50}
    # The same again changes nothing on the board: still answered, from a later report.
    got = await rpc.call("machine.override", machine=GRBL, feed=90)
    assert got == {"feed": 90, "spindle": 80, "rapid": 50}
    snap = await rpc.call("machine.status", machine=GRBL)
    assert snap["overrides"] == {"feed": 90, "rapid": 50, "spindle": 80}


async def test_a_second_operation_while_one_runs_is_busy(both: tuple[Running, Rpc]) -> None:
    hostd, rpc = both
    await jog_to(hostd, rpc, G2, {"x": 6})
    first, second = await asyncio.gather(
        rpc.call("machine.home", machine=G2),
        fails(1003, rpc.call("machine.goto_zero", machine=G2)),
        return_exceptions=True,
    )
    assert first == {}, first
    assert isinstance(second, RpcFailure) and "operation" in second.message
    assert not any(line.startswith(b"G90 G0") for line in lines_sent(hostd, G2))


async def test_operations_on_a_disconnected_machine_are_1002(both: tuple[Running, Rpc]) -> None:
    _, rpc = both
    await rpc.call("machine.disconnect", machine=G2)
    await fails(1002, rpc.call("machine.home", machine=G2))
    await fails(1002, rpc.call("machine.zero", machine=G2, axes={"x": 0}))
    await fails(1002, rpc.call("machine.spindle", machine=G2, state="off"))
