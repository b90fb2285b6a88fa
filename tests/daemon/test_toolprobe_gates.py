"""Tool changes and probing: what the operator would notice that test_toolchange.py and
test_probing.py leave open (a hand-run mutation campaign on hostd/machine/toolchange.py
and hostd/machine/probing.py found each of these unpinned).

A real daemon with a simulated g2core (sim1) and a simulated grbl (sim2) on real ptys,
reached through the real socket.
"""

from __future__ import annotations

import asyncio
from collections.abc import Coroutine
from pathlib import Path
from typing import Any

import pytest

from hostd.machine import probing
from hostd.sim.probing import TouchPlate
from tests.daemon.conftest import G2, GRBL, Rpc, RpcFailure, Running
from tests.daemon.test_api import fails, job_end
from tests.daemon.test_operations import lines_sent
from tests.daemon.test_probing import (
    FAST,
    PLATE,
    TOP,
    assert_zeroed_over_the_plate,
    moves_sent,
    sim_of,
    touch,
)
from tests.daemon.test_toolchange import (
    MACHINES,
    SENSOR_Z,
    _daemon,
    _spindle_of,
    _start,
    _unnumbered,
    _waiting,
)

pytestmark = pytest.mark.asyncio

# A sensor whose X and Y differ (test_toolchange.py's sits at X-5 Y-5): a measurement
# that mixed them up would go down beside it.
SENSOR = {"x": -5.0, "y": -8.0}
PROBE = {"feed": 600.0, "max_travel": 25.0, "tool_sensor": SENSOR}
# Tool 2's change comes with the tool at X2.345 Y1.25; the job's next line moves only Z.
OFF_AXIS = "G21 G90\nG0 X0 Y0 Z0\nT1 M6\nG0 X2.345 Y1.25\nT2 M6\nG0 Z-5\nM2\n"


@pytest.mark.parametrize("machine", MACHINES)
async def test_a_measured_tool_goes_down_over_the_sensor_and_comes_back_where_it_stopped(
    tmp_path: Path, machine: str
) -> None:
    """The sensor at X-5 Y-8: the tool goes down over it, not at X-8 Y-5 (beside it,
    into the table), and after the measuring it comes back over X2.345 Y1.25, where the
    job left it (not swapped, nor rounded): the job's next cut starts where the program says."""
    async with _daemon(tmp_path, "probe", probe=PROBE, safe_z=0.0) as (running, rpc):
        running.daemon.sims[machine].tool_sensor(SENSOR["x"], SENSOR["y"], SENSOR_Z)
        job_id = await _start(rpc, machine, "offaxis.nc", OFF_AXIS)
        await _waiting(rpc, machine, job_id, 3)
        await rpc.call("job.tool_change_done", machine=machine)
        waiting = await _waiting(rpc, machine, job_id, 5, changes=1)
        assert waiting["machine_position"]["x"] == pytest.approx(2.345, abs=0.002)
        assert waiting["machine_position"]["y"] == pytest.approx(1.25, abs=0.002)
        await rpc.call("job.tool_change_done", machine=machine)
        measured = await rpc.call("machine.status", machine=machine)
        assert measured["probe"]["ok"] is True
        assert measured["probe"]["position"]["z"] == pytest.approx(SENSOR_Z, abs=0.01)
        done = await job_end(rpc, job_id)
        assert done["state"] == "completed", done
        end = await rpc.call("machine.status", machine=machine)
        assert end["machine_position"]["x"] == pytest.approx(2.345, abs=0.002)
        assert end["machine_position"]["y"] == pytest.approx(1.25, abs=0.002)
        assert end["machine_position"]["z"] == pytest.approx(-5.0, abs=0.01)


@pytest.mark.parametrize("machine", MACHINES)
async def test_a_tool_change_cannot_be_answered_while_the_operators_jog_still_moves(
    tmp_path: Path, machine: str
) -> None:
    """The operator jogs up at a tool change and answers before the jog has ended: the
    answer is refused (1003, "let it come to rest"), the job keeps waiting, and once
    the board rests the same answer goes through."""
    async with _daemon(tmp_path, "pause", safe_z=0.0) as (_, rpc):
        job_id = await _start(rpc, machine, "two.nc", "G0 X1\nT1 M6\nG0 X0\n")
        await _waiting(rpc, machine, job_id, 2)
        await rpc.call("subscribe", topics=["status"], machine=machine)
        await rpc.call("machine.jog", machine=machine, axes={"z": 3.0}, feed=60)
        await rpc.notification(
            lambda n: (
                n["method"] == "status"
                and 0.1 < n["params"]["snapshot"]["machine_position"]["z"] < 2.5
            )
        )
        err = await fails(1003, rpc.call("job.tool_change_done", machine=machine))
        assert "rest" in err.message
        still = await rpc.call("machine.status", machine=machine)
        assert still["tool_change"] == {"tool": 1, "line": 2}
        await rpc.notification(
            lambda n: (
                n["method"] == "status"
                and n["params"]["snapshot"]["state"]["name"] in ("READY", "PROGRAM_STOP", "IDLE")
                and n["params"]["snapshot"]["machine_position"]["z"] == pytest.approx(3.0)
            )
        )
        job = await rpc.call("job.tool_change_done", machine=machine)
        assert [c["tool"] for c in job["tool_changes"]] == [1]
        assert (await job_end(rpc, job_id))["state"] == "completed"


# The laser on (M4, dynamic power) when the job reaches its M6 (line 4).
LASER = "G21 G90\nM4 S500\nG1 X1 F3000\nT2 M6\nG1 X2\nM5\nM2\n"


async def test_a_laser_comes_back_on_after_a_tool_change_without_a_spin_up_dwell(
    tmp_path: Path,
) -> None:
    """The simulated grbl is a laser ($32=1): its beam has no speed to reach, so no
    `spindle_dwell` is waited after `M4` (a standing beam would burn a spot)."""
    async with _daemon(tmp_path, "pause", spindle_dwell=0.5) as (running, rpc):
        assert (await rpc.call("machine.status", machine=GRBL))["laser_mode"] is True
        job_id = await _start(rpc, GRBL, "laser.nc", LASER)
        await _waiting(rpc, GRBL, job_id, 4)
        before = len(lines_sent(running, GRBL))
        await rpc.call("job.tool_change_done", machine=GRBL)
        assert (await job_end(rpc, job_id))["state"] == "completed"
        after = [ln for ln in _unnumbered(lines_sent(running, GRBL))[before:] if ln != b"$G"]
        assert after[0] == b"M4 S500", after
        assert not any(line.startswith(b"G4") for line in after), after


async def test_ignore_sends_g2core_the_m6_line_without_its_m6(tmp_path: Path) -> None:
    """Under "ignore" the M6 is taken out as the job is read: g2core runs the line's
    other words (its T) and no tool change of its own."""
    async with _daemon(tmp_path, "ignore") as (running, rpc):
        job_id = await _start(rpc, G2, "two.nc", "G0 X1\nT2 M6\nG0 X0\n")
        assert (await job_end(rpc, job_id))["state"] == "completed"
        sent = _unnumbered(lines_sent(running, G2))
        assert b"T2" in sent and not any(b"M6" in line for line in sent), sent


@pytest.mark.parametrize(("line", "state"), [("M3 S5000", "cw"), ("M4 S5000", "ccw")])
async def test_a_spindle_the_operator_started_before_the_job_is_stopped_at_its_tool_change(
    tmp_path: Path, line: str, state: str
) -> None:
    """The job's lines never turn the spindle on, but the operator did (`M3` or `M4`
    before starting it) and the board reports it running: it is stopped (`M5`) before the
    operator is told to change the tool, and not turned on again after."""
    async with _daemon(tmp_path, "pause") as (running, rpc):
        await rpc.call("subscribe", topics=["status"], machine=G2)
        await rpc.call("machine.send", machine=G2, line=line)
        await rpc.notification(
            lambda n: (
                n["method"] == "status"
                and (n["params"]["snapshot"]["spindle"] or {}).get("state") == state
            )
        )
        job_id = await _start(rpc, G2, "plain.nc", "G0 X1\nT2 M6\nG0 X0\n")
        await _waiting(rpc, G2, job_id, 2)
        assert _spindle_of(running, G2) == "M5"
        await rpc.call("job.tool_change_done", machine=G2)
        assert (await job_end(rpc, job_id))["state"] == "completed"
        assert _spindle_of(running, G2) == "M5"


# One tool, measured at the job's start; the job then goes down to Z-5.
ONE_TOOL = "G21 G90\nG0 X0 Y0 Z0\nT1 M6\nG0 Z-5\nM2\n"


@pytest.mark.parametrize("machine", MACHINES)
async def test_each_job_measures_its_own_reference_tool(tmp_path: Path, machine: str) -> None:
    """Between two jobs the operator puts in a tool 3 mm longer and sets work Z for it:
    the second job's first measurement is its own reference, so its Z-5 is Z-5, not
    3 mm higher for the difference to the first job's tool."""
    async with _daemon(tmp_path, "probe", probe=PROBE, safe_z=0.0) as (running, rpc):
        sim = running.daemon.sims[machine]
        sim.tool_sensor(SENSOR["x"], SENSOR["y"], SENSOR_Z)
        for name, length in (("first.nc", 0.0), ("second.nc", 3.0)):
            sim.tool_length(length)
            job_id = await _start(rpc, machine, name, ONE_TOOL)
            await _waiting(rpc, machine, job_id, 3)
            await rpc.call("job.tool_change_done", machine=machine)
            measured = await rpc.call("machine.status", machine=machine)
            assert measured["probe"]["position"]["z"] == pytest.approx(SENSOR_Z + length, abs=0.01)
            assert (await job_end(rpc, job_id))["state"] == "completed"
            end = await rpc.call("machine.status", machine=machine)
            assert end["machine_position"]["z"] == pytest.approx(-5.0, abs=0.01), name
            await running.idle(rpc, machine)


SETTLE = 0.0125  # a pause no other part of the daemon asks for


async def test_the_probe_waits_for_the_operators_hands_to_leave_the_plate_before_moving(
    both: tuple[Running, Rpc], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Seen working (closed, then open), the probe first gives the operator's hands
    `SETTLE` seconds off the plate: nothing moves before that pause."""
    hostd, rpc = both
    monkeypatch.setattr(probing, "SETTLE", SETTLE)
    real_sleep = asyncio.sleep
    moved_at_pause: list[int] = []

    def sleep(delay: float, *args: Any, **kwargs: Any) -> Coroutine[Any, Any, Any]:
        if delay == SETTLE:
            moved_at_pause.append(len(moves_sent(hostd, G2)))
        return real_sleep(delay, *args, **kwargs)

    monkeypatch.setattr(asyncio, "sleep", sleep)
    sim_of(hostd, G2).touch_plate(TouchPlate(top=TOP))
    touch(hostd, G2)
    await rpc.call("machine.probe", machine=G2, kind="z", plate=PLATE, **FAST)
    assert moved_at_pause == [0]


# The spindle on at 8000 rpm when the job reaches its M6 (line 4).
SPINNING = "G21 G90\nG0 X0 Y0 Z0\nM3 S8000\nT2 M6\nG0 X2\nM5\nM2\n"


async def test_a_second_answer_while_the_first_is_under_way_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two operators (or a double click) answer the same tool change: the one the
    daemon takes first goes on, the other is 1003 "already being answered", and the
    job records the change once."""
    async with _daemon(tmp_path, "pause", spindle_dwell=0.05) as (running, rpc):
        engine = running.daemon.machines[G2].engine
        send = engine.send
        entered, release = asyncio.Event(), asyncio.Event()

        async def held_send(line: str, **kwargs: Any) -> Any:
            if line.startswith("M3"):  # the first answer turns the spindle back on
                entered.set()
                await release.wait()
            return await send(line, **kwargs)

        job_id = await _start(rpc, G2, "spin.nc", SPINNING)
        await _waiting(rpc, G2, job_id, 4)
        monkeypatch.setattr(engine, "send", held_send)
        try:
            first = asyncio.create_task(rpc.call("job.tool_change_done", machine=G2))
            await entered.wait()
            other = await running.client()
            err = await fails(
                1003, asyncio.wait_for(other.call("job.tool_change_done", machine=G2), 10)
            )
            assert "already being answered" in err.message
            await other.close()
        finally:
            release.set()
        job = await first
        assert [c["tool"] for c in job["tool_changes"]] == [2]
        done = await job_end(rpc, job_id)
        assert done["state"] == "completed"
        recorded = (await rpc.call("job.get", job=job_id))["tool_changes"]
        assert [c["tool"] for c in recorded] == [2]


@pytest.mark.parametrize("machine", MACHINES)
async def test_a_job_cancelled_while_its_tool_is_measured_does_not_start_the_spindle(
    tmp_path: Path, machine: str
) -> None:
    """The job had the spindle on at its M6; the operator cancels while the new tool
    is on its way to the sensor: the answer fails, the job ends cancelled, and the
    spindle stays off (it comes back on only for a job that goes on)."""
    async with _daemon(tmp_path, "probe", probe=PROBE, safe_z=0.0) as (running, rpc):
        if machine == GRBL:  # the simulated grbl is a laser ($32=1): make it a mill
            await rpc.call("settings.set", machine=machine, values={"32": 0})
            await rpc.call("settings.get", machine=machine, keys=["32"])
        running.daemon.sims[machine].tool_sensor(SENSOR["x"], SENSOR["y"], SENSOR_Z)
        job_id = await _start(rpc, machine, "spin.nc", SPINNING)
        await _waiting(rpc, machine, job_id, 4)
        assert _spindle_of(running, machine) == "M5"
        await rpc.call("subscribe", topics=["status"], machine=machine)
        answering = asyncio.create_task(rpc.call("job.tool_change_done", machine=machine))
        await rpc.notification(
            lambda n: (
                n["method"] == "status" and n["params"]["snapshot"]["machine_position"]["x"] < -1
            )
        )
        await rpc.call("job.cancel", machine=machine)
        assert (await job_end(rpc, job_id))["state"] == "cancelled"
        with pytest.raises(RpcFailure):
            await answering
        await running.idle(rpc, machine)
        assert _spindle_of(running, machine) == "M5"
        sent = _unnumbered(lines_sent(running, machine))
        assert sent.count(b"M3 S8000") == 1, sent


# The job leaves the tool at Z-5 (under the safe height, Z0) before its M6 at line 4.
LOW = "G21 G90\nG0 X0 Y0 Z0\nG0 X2 Z-5\nT1 M6\nG0 X3\nM2\n"


@pytest.mark.parametrize("machine", MACHINES)
async def test_a_measurement_lifts_to_the_safe_height_before_crossing_to_the_sensor(
    tmp_path: Path, machine: str
) -> None:
    """The tool stands at Z-5, down in the work: it goes straight up to the safe height
    first, and only then across to the sensor (never across at Z-5, through clamps),
    and goes down onto it at the probe's feed."""
    async with _daemon(tmp_path, "probe", probe=PROBE, safe_z=0.0) as (running, rpc):
        running.daemon.sims[machine].tool_sensor(SENSOR["x"], SENSOR["y"], SENSOR_Z)
        job_id = await _start(rpc, machine, "low.nc", LOW)
        await _waiting(rpc, machine, job_id, 4)
        before = len(lines_sent(running, machine))
        await rpc.call("job.tool_change_done", machine=machine)
        assert (await job_end(rpc, job_id))["state"] == "completed"
        sent = _unnumbered(lines_sent(running, machine))[before:]
        moves = [line for line in sent if line.startswith(b"G53")]
        assert moves[:2] == [b"G53 G0 Z0", b"G53 G0 X-5 Y-8"], moves
        # Down at the probe's feed (a sensor is not a thing to rush into), within its travel.
        assert b"G91 G38.2 Z-25 F600" in sent, sent


# An inch program: X0.1 is 2.54 mm. Its M6 at line 3.
INCHES = "G20 G90\nG0 X0 Y0 Z0\nT1 M6\nG0 X0.1\nM2\n"


@pytest.mark.parametrize("machine", MACHINES)
async def test_a_tool_of_an_inch_program_is_measured_in_mm_and_the_program_stays_in_inches(
    tmp_path: Path, machine: str
) -> None:
    """The sensor's place and the probe's travel are mm: in a G20 program they are
    still reached (not 25.4 times as far), and the program's next X0.1 is 2.54 mm."""
    async with _daemon(tmp_path, "probe", probe=PROBE, safe_z=0.0) as (running, rpc):
        running.daemon.sims[machine].tool_sensor(SENSOR["x"], SENSOR["y"], SENSOR_Z)
        job_id = await _start(rpc, machine, "inches.nc", INCHES)
        await _waiting(rpc, machine, job_id, 3)
        await rpc.call("job.tool_change_done", machine=machine)
        measured = await rpc.call("machine.status", machine=machine)
        assert measured["probe"]["ok"] is True
        assert (await job_end(rpc, job_id))["state"] == "completed"
        end = await rpc.call("machine.status", machine=machine)
        assert end["units"] == "in"
        scale = 25.4 if end["position_units"]["machine"] == "in" else 1.0
        assert end["machine_position"]["x"] * scale == pytest.approx(2.54, abs=0.01)


# A CAM program that applies each tool's length itself (`G43 H<tool>`) after its M6.
CAM = "G21 G90\nG0 X0 Y0 Z0\nT1 M6\nG43 H1\nG0 X1\nT2 M6\nG43 H2\nG0 Z-5\nM2\n"


async def test_g2core_keeps_each_measured_length_in_its_tools_own_table_entry(
    tmp_path: Path,
) -> None:
    """g2core: tool 2's measured length goes into tool table entry 2, so the program's
    own `G43 H2` after the change keeps the 3 mm longer tool 3 mm higher (entry 1 would
    leave entry 2 empty, and the program's Z-5 would cut 3 mm too deep)."""
    async with _daemon(tmp_path, "probe", probe=PROBE, safe_z=0.0) as (running, rpc):
        sim = running.daemon.sims[G2]
        sim.tool_sensor(SENSOR["x"], SENSOR["y"], SENSOR_Z)
        job_id = await _start(rpc, G2, "cam.nc", CAM)
        await _waiting(rpc, G2, job_id, 3)
        await rpc.call("job.tool_change_done", machine=G2)
        await _waiting(rpc, G2, job_id, 6, changes=1)
        sim.tool_length(3.0)
        await rpc.call("job.tool_change_done", machine=G2)
        assert (await job_end(rpc, job_id))["state"] == "completed"
        end = await rpc.call("machine.status", machine=G2)
        assert end["machine_position"]["z"] == pytest.approx(-2.0, abs=0.01)


@pytest.mark.parametrize("machine", MACHINES)
async def test_a_board_in_inches_is_back_in_inches_after_the_probe(
    both: tuple[Running, Rpc], machine: str
) -> None:
    """The probe moves in mm (`G21`); a board the operator had in G20 is given G20
    back, so their next `G0 X1` is still an inch."""
    hostd, rpc = both
    sim_of(hostd, machine).touch_plate(TouchPlate(top=TOP))
    await rpc.call("machine.send", machine=machine, line="G20")
    touch(hostd, machine)
    result = await rpc.call("machine.probe", machine=machine, kind="z", plate=PLATE, **FAST)
    assert result["position"]["z"] == pytest.approx(TOP, abs=0.003)
    assert [line for line in lines_sent(hostd, machine) if line[:1] == b"G"][-1] == b"G20"
    assert (await rpc.call("machine.status", machine=machine))["units"] == "in"


@pytest.mark.parametrize("machine", MACHINES)
async def test_a_corner_probe_backs_off_each_wall_away_from_the_plate(
    both: tuple[Running, Rpc], machine: str
) -> None:
    """After touching a wall (probing towards +X, then +Y) the bit backs off `retract`
    away from it, the way it came, before it rises: not on into the plate."""
    hostd, rpc = both
    plate = TouchPlate(top=TOP, x_face=-2.5, y_face=-2.5, tool_radius=1.5)
    sim_of(hostd, machine).touch_plate(plate)
    touch(hostd, machine)
    await rpc.call(
        "machine.probe", machine=machine, kind="xyz", plate=PLATE, tool_diameter=3.0, **FAST
    )
    moves = moves_sent(hostd, machine)
    for axis in (b"X", b"Y"):
        wall = next(i for i, m in enumerate(moves) if m.startswith(b"G38.2 " + axis))
        back = next(m for m in moves[wall + 1 :] if m.startswith(b"G0 "))
        assert back.startswith(b"G0 " + axis), moves
        # Zeroed for the wall: the touch reads -(plate + radius) = -11.5; backed off, less.
        assert float(back[4:]) == pytest.approx(-(PLATE + 1.5) - FAST["retract"], abs=0.01)


async def test_a_board_that_alarms_while_the_operators_hands_leave_the_plate_is_not_probed(
    both: tuple[Running, Rpc], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The input was seen working, and during the pause for the operator's hands the
    board goes into its alarm (an e-stop, a limit): the probe stops there, 1003
    "nothing was moved", and not one line of it is sent."""
    hostd, rpc = both
    engine = hostd.daemon.machines[G2].engine
    monkeypatch.setattr(probing, "SETTLE", SETTLE)
    real_sleep = asyncio.sleep

    async def sleep(delay: float, *args: Any, **kwargs: Any) -> Any:
        if delay == SETTLE:
            await engine.alarm()
            await engine.wait_for(engine.session.locked)
        return await real_sleep(delay, *args, **kwargs)

    sim_of(hostd, G2).touch_plate(TouchPlate(top=TOP))
    touch(hostd, G2)
    monkeypatch.setattr(asyncio, "sleep", sleep)
    err = await fails(1003, rpc.call("machine.probe", machine=G2, kind="z", plate=PLATE, **FAST))
    assert "nothing was moved" in err.message
    sent = lines_sent(hostd, G2)
    assert b"G21 G90" not in sent and not any(line.startswith(b"G38") for line in sent), sent


@pytest.mark.parametrize("machine", MACHINES)
async def test_a_corner_probe_started_too_far_from_the_corner_stops_on_the_plate(
    both: tuple[Running, Rpc], machine: str
) -> None:
    """The bit starts 8 mm in from each wall, more than half the travel (5 mm): going
    down beside the plate it meets the plate's top instead. The probe stops there
    (1003, "start it over the plate nearer the corner") and never drives sideways
    into a wall it is not beside."""
    hostd, rpc = both
    plate = TouchPlate(top=TOP, x_face=-8.0, y_face=-8.0, tool_radius=1.5)
    sim_of(hostd, machine).touch_plate(plate)
    touch(hostd, machine)
    err = await fails(
        1003,
        rpc.call(
            "machine.probe", machine=machine, kind="xyz", plate=PLATE, tool_diameter=3.0, **FAST
        ),
    )
    assert "met the plate going down beside it" in err.message
    assert not any(m.startswith((b"G38.2 X", b"G38.2 Y")) for m in moves_sent(hostd, machine))


async def test_a_slow_probe_is_waited_for_as_long_as_its_travel_takes(
    both: tuple[Running, Rpc],
) -> None:
    """At 1.5 mm/min the 3 mm down to the plate take longer than a line's answer is
    waited for (10 s, even on the quickened simulator): the probe waits for its touch
    all the same, for as long as its travel at its feed takes."""
    hostd, rpc = both
    sim_of(hostd, G2).touch_plate(TouchPlate(top=TOP))
    touch(hostd, G2)
    slow = {**FAST, "feed": 1.5, "max_travel": 4.0}
    result = await rpc.call("machine.probe", machine=G2, kind="z", plate=PLATE, **slow)
    assert result["position"]["z"] == pytest.approx(TOP)


@pytest.mark.parametrize(("machine", "status"), [(G2, 250), (GRBL, 0)])
async def test_a_probe_that_misses_carries_the_boards_own_status(
    both: tuple[Running, Rpc], machine: str, status: int
) -> None:
    """A miss is 1005 with the board's status in its data: g2core's 250 (its probe
    alarm), grbl's alarm has none (0)."""
    hostd, rpc = both
    touch(hostd, machine)  # works when touched, but no plate is under the bit
    err = await fails(
        1005, rpc.call("machine.probe", machine=machine, kind="z", plate=PLATE, **FAST)
    )
    assert err.data["status"] == status, err.data


@pytest.mark.parametrize("machine", MACHINES)
async def test_a_corner_probe_over_an_old_work_zero_sets_the_new_one_and_comes_back(
    both: tuple[Running, Rpc], machine: str
) -> None:
    """A work zero from the last job is still set (work X, Y, Z read 5 at machine 0):
    the probe zeroes from the machine positions all the same, and goes back to where
    it started in machine coordinates, not to the old work zero's numbers."""
    hostd, rpc = both
    await _old_work_zero(rpc, machine)
    plate = TouchPlate(top=TOP, x_face=-2.5, y_face=-2.5, tool_radius=1.5)
    sim_of(hostd, machine).touch_plate(plate)
    touch(hostd, machine)
    await rpc.call(
        "machine.probe", machine=machine, kind="xyz", plate=PLATE, tool_diameter=3.0, **FAST
    )
    snap = await rpc.call("machine.status", machine=machine)
    assert_zeroed_over_the_plate(snap)


@pytest.mark.parametrize("machine", MACHINES)
async def test_a_miss_over_an_old_work_zero_says_where_it_stopped_in_machine_mm(
    both: tuple[Running, Rpc], machine: str
) -> None:
    """The miss says where the board stopped in machine coordinates, as it says it
    does, whatever the work zero left from the last job."""
    hostd, rpc = both
    await _old_work_zero(rpc, machine)
    touch(hostd, machine)
    err = await fails(
        1005, rpc.call("machine.probe", machine=machine, kind="z", plate=PLATE, **FAST)
    )
    assert "the board stopped at X0.000, Y0.000, Z-10.000 (machine, mm)" in err.message


async def _old_work_zero(rpc: Rpc, machine: str) -> None:
    """Work X, Y and Z read 5 where the tool stands (machine 0): G54's offsets -5."""
    p = 0 if machine == GRBL else 1
    await rpc.call("subscribe", topics=["status"], machine=machine)
    await rpc.call("machine.send", machine=machine, line=f"G10 L20 P{p} X5 Y5 Z5")
    await rpc.notification(
        lambda n: (
            n["method"] == "status"
            and n["params"]["snapshot"]["work_position"]["z"] == pytest.approx(5.0, abs=0.001)
        )
    )
