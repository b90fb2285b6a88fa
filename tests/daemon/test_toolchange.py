"""Tool changes (issue 29): a job's M6 under each `tool_change` policy, on both dialects.

A real daemon with a simulated g2core (sim1) and a simulated grbl (sim2) on real
ptys, reached through the real socket. grbl's simulator refuses M6 as grbl does
(error:20), so a grbl job that completes is one whose M6 never reached the board.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio

from hostd.sim import SimController
from tests.daemon.conftest import G2, GRBL, Rpc, RpcFailure, Running, running_daemon
from tests.daemon.test_api import fails, job_end
from tests.daemon.test_operations import lines_sent

pytestmark = pytest.mark.asyncio

MACHINES = (G2, GRBL)
# Tool 1 at line 3 (nothing moved yet), tool 2 at line 6, after two moves to X2.
TWO_TOOLS = "G21 G90\nG0 X0 Y0 Z0\nT1 M6\nG0 X1\nG1 X2 F3000\nT2 M6 (second tool)\nG0 X3\nM2\n"
LINES = 8


@contextlib.asynccontextmanager
async def _daemon(tmp_path: Path, policy: str, **extra: Any) -> AsyncIterator[tuple[Running, Rpc]]:
    per = [{"tool_change": policy}, {"dialect": "grbl", "tool_change": policy}]
    async with running_daemon(tmp_path, machines=2, per_machine=per, plunge_feed=300, **extra) as d:
        client = await d.client()
        for machine in MACHINES:
            await d.idle(client, machine)
        yield d, client
        await client.close()


@pytest_asyncio.fixture
async def paused(tmp_path: Path) -> AsyncIterator[tuple[Running, Rpc]]:
    # A safe height of their own: these boards are never homed, and a recovery plans
    # from it (Machine.safe_height: the Z travel's top counts only on a homed machine).
    async with _daemon(tmp_path, "pause", safe_z=0.0) as both:
        yield both


async def _waiting(
    rpc: Rpc, machine: str, job_id: int, line: int, changes: int = 0
) -> dict[str, Any]:
    """Until the job holds at the M6 of `line`, with `changes` tool changes made before
    (a paused job is published again while it waits); the snapshot then."""
    await rpc.notification(
        lambda n: (
            n["method"] == "job"
            and n["params"]["job"]["id"] == job_id
            and n["params"]["job"]["state"] != "running"
            and len(n["params"]["job"]["tool_changes"]) == changes
        )
    )
    snapshot: dict[str, Any] = await rpc.call("machine.status", machine=machine)
    assert snapshot["tool_change"] is not None and snapshot["tool_change"]["line"] == line
    return snapshot


def _rests_at(note: dict[str, Any], **where: float) -> bool:
    snapshot = note["params"]["snapshot"]
    position = snapshot["machine_position"]
    return snapshot["state"]["name"] in ("READY", "PROGRAM_STOP") and all(
        abs(position[axis] - value) < 0.01 for axis, value in where.items()
    )


async def _start(rpc: Rpc, machine: str, name: str, data: str) -> int:
    await rpc.call("file.upload", name=name, data=data)
    await rpc.call("subscribe", topics=["job"], machine=machine)
    started = await rpc.call("job.start", machine=machine, file=name)
    return int(started["job"])


@pytest.mark.parametrize("machine", MACHINES)
async def test_pause_holds_at_each_m6_and_goes_on_when_told(
    paused: tuple[Running, Rpc], machine: str
) -> None:
    _, rpc = paused
    job_id = await _start(rpc, machine, "two.nc", TWO_TOOLS)

    first = await _waiting(rpc, machine, job_id, 3)
    assert first["tool_change"] == {"tool": 1, "line": 3}
    assert first["supervisor"] == "paused" and first["job"]["state"] == "paused"
    # job.resume does not carry the job past the change; job.pause has nothing to pause.
    await fails(1003, rpc.call("job.resume", machine=machine))
    job = await rpc.call("job.tool_change_done", machine=machine)
    assert job["id"] == job_id and [c["tool"] for c in job["tool_changes"]] == [1]
    # The tool the operator put in is the machine's (grbl's `$G` may still say T0).
    assert (await rpc.call("machine.status", machine=machine))["tool"] == 1

    second = await _waiting(rpc, machine, job_id, 6, changes=1)
    assert second["tool_change"] == {"tool": 2, "line": 6}
    # The board ran every line before the M6 before the job held: it stands at X2.
    assert second["machine_position"]["x"] == pytest.approx(2.0, abs=0.01)
    assert second["state"]["name"] in ("READY", "PROGRAM_STOP")
    # The operator may jog while the job waits: the jog moves the board, the job stays.
    await rpc.call("subscribe", topics=["status"], machine=machine)
    jogged = await rpc.call("machine.jog", machine=machine, axes={"z": 1.0}, feed=600)
    assert jogged["job"] == job_id
    await rpc.notification(lambda n: n["method"] == "status" and _rests_at(n, z=1.0))
    # `~` is a plain cycle start here (for a jog held with `!`): the job keeps waiting.
    assert await rpc.call("machine.cycle_start", machine=machine) == {}
    still = await rpc.call("machine.status", machine=machine)
    assert still["tool_change"] == {"tool": 2, "line": 6} and still["supervisor"] == "paused"
    await rpc.call("job.tool_change_done", machine=machine)

    done = await job_end(rpc, job_id)
    assert done["state"] == "completed", done
    assert done["lines_acked"] == LINES and done["error"] is None
    changes = (await rpc.call("job.get", job=job_id))["tool_changes"]
    assert [(c["tool"], c["line"]) for c in changes] == [(1, 3), (2, 6)]
    assert all(isinstance(c["at"], str) and c["at"].endswith("Z") for c in changes)
    after = await rpc.call("machine.status", machine=machine)
    assert after["tool_change"] is None and after["tool"] == 2
    assert after["machine_position"]["x"] == pytest.approx(3.0, abs=0.01)


@pytest.mark.parametrize("machine", MACHINES)
async def test_no_tool_change_to_answer(paused: tuple[Running, Rpc], machine: str) -> None:
    _, rpc = paused
    await fails(1003, rpc.call("job.tool_change_done", machine=machine))
    await fails(1001, rpc.call("job.tool_change_done", machine="nope"))


@pytest.mark.parametrize("machine", MACHINES)
async def test_cancel_while_waiting_ends_the_job(paused: tuple[Running, Rpc], machine: str) -> None:
    running, rpc = paused
    job_id = await _start(rpc, machine, "two.nc", TWO_TOOLS)
    await _waiting(rpc, machine, job_id, 3)
    cancelled = await rpc.call("job.cancel", machine=machine)
    assert cancelled["state"] == "cancelled" and cancelled["tool_changes"] == []
    await running.idle(rpc, machine)
    status = await rpc.call("machine.status", machine=machine)
    assert status["tool_change"] is None and status["supervisor"] == "idle"
    await fails(1003, rpc.call("job.tool_change_done", machine=machine))
    # The machine takes the next job as usual.
    again = await _start(rpc, machine, "plain.nc", "G0 X1\nG0 X0\n")
    assert (await job_end(rpc, again))["state"] == "completed"


@pytest.mark.parametrize("machine", MACHINES)
async def test_a_link_lost_while_waiting_leaves_an_interrupted_job(
    paused: tuple[Running, Rpc], machine: str
) -> None:
    running, rpc = paused
    job_id = await _start(rpc, machine, "two.nc", TWO_TOOLS)
    await _waiting(rpc, machine, job_id, 3)
    await running.daemon.sims[machine].unplug()
    ended = await job_end(rpc, job_id)
    assert ended["state"] == "interrupted" and ended["error"]["code"] == 1002
    assert (await rpc.call("machine.status", machine=machine))["tool_change"] is None
    await fails(1003, rpc.call("job.tool_change_done", machine=machine))
    await running.daemon.sims[machine].replug()
    await running.idle(rpc, machine)  # back, and free: nothing waits any more
    assert (await rpc.call("job.get", job=job_id))["state"] == "interrupted"


@pytest.mark.parametrize("machine", MACHINES)
async def test_a_job_whose_link_was_lost_at_a_tool_change_is_recovered_as_any_other(
    paused: tuple[Running, Rpc], machine: str
) -> None:
    """Held at the first M6 (line 3) the board has run lines 1-2 and rests: the job's
    place is the M6 line. Line 2 could not be resumed (no position is known before
    it), which made job.recovery answer 1011."""
    running, rpc = paused
    job_id = await _start(rpc, machine, "two.nc", TWO_TOOLS)
    await _waiting(rpc, machine, job_id, 3)
    await running.daemon.sims[machine].unplug()
    ended = await job_end(rpc, job_id)
    assert ended["state"] == "interrupted" and ended["line_executed"] == 3, ended
    await running.daemon.sims[machine].replug()
    await running.idle(rpc, machine)
    plan = await rpc.call("job.recovery", job=job_id)
    assert plan["file"] == "two.nc" and plan["line"] == 3, plan
    assert plan["position"]["x"] == pytest.approx(0.0) and plan["preamble"], plan
    # Resumed there, it holds at that M6 again and asks for tool 1 (grbl: the T word).
    started = await rpc.call("job.start", machine=machine, file="two.nc", start_line=3)
    resumed = int(started["job"])
    snapshot = await _waiting(rpc, machine, resumed, 3)
    assert snapshot["tool_change"] == {"tool": 1, "line": 3}
    await rpc.call("job.tool_change_done", machine=machine)
    await _waiting(rpc, machine, resumed, 6, changes=1)
    await rpc.call("job.tool_change_done", machine=machine)
    assert (await job_end(rpc, resumed))["state"] == "completed"


async def test_a_daemon_stopped_while_waiting_leaves_a_recoverable_job(tmp_path: Path) -> None:
    async with _daemon(tmp_path, "pause", safe_z=0.0) as (_, rpc):
        job_id = await _start(rpc, GRBL, "two.nc", TWO_TOOLS)
        await _waiting(rpc, GRBL, job_id, 3)
        await rpc.call("job.tool_change_done", machine=GRBL)
        await _waiting(rpc, GRBL, job_id, 6, changes=1)
    async with _daemon(tmp_path, "pause", safe_z=0.0) as (_, rpc):
        job = await rpc.call("job.get", job=job_id)
        assert job["state"] == "interrupted"
        assert [(c["tool"], c["line"]) for c in job["tool_changes"]] == [(1, 3)]
        plan = await rpc.call("job.recovery", job=job_id)
        assert plan["file"] == "two.nc" and plan["line"] == 6  # the M6 it waited at
        assert (await rpc.call("machine.status", machine=GRBL))["tool_change"] is None


@pytest.mark.parametrize("policy", ["pause", "probe", "ignore", "refuse"])
async def test_analyze_says_what_the_machines_policy_does_with_each_m6(
    tmp_path: Path, policy: str
) -> None:
    """grbl's G-code lacks M6, but the host handles it: file.analyze warns as the
    machine's tool_change takes it, the same on both dialects, never "not supported"."""
    probe = {"feed": 600.0, "max_travel": 25.0, "tool_sensor": SENSOR}
    async with _daemon(tmp_path, policy, probe=probe) as (_, rpc):
        await rpc.call("file.upload", name="two.nc", data=TWO_TOOLS)
        for machine in MACHINES:
            analysis = await rpc.call("file.analyze", file="two.nc", machine=machine)
            warnings = analysis["warnings"]
            assert not any("not supported" in w for w in warnings), (machine, warnings)
            m6 = [w for w in warnings if "M6" in w]
            problems = [p["line"] for p in analysis["problems"]]
            if policy in ("pause", "probe"):  # the job holds at each: nothing to warn of
                assert m6 == [] and problems == [], (machine, warnings)
            elif policy == "ignore":
                assert [w.split(":")[0] for w in m6] == ["line 3", "line 6"], m6
                assert all("stripped" in w and "'ignore'" in w for w in m6), m6
                assert problems == []
            else:
                assert [w.split(":")[0] for w in m6] == ["line 3", "line 6"], m6
                assert all("refused" in w and "'refuse'" in w for w in m6), m6
                assert problems == [3, 6]


@pytest.mark.parametrize("machine", MACHINES)
async def test_ignore_strips_the_m6_with_a_warning(tmp_path: Path, machine: str) -> None:
    async with _daemon(tmp_path, "ignore") as (_, rpc):
        await rpc.call("file.upload", name="two.nc", data=TWO_TOOLS)
        analysis = await rpc.call("file.analyze", file="two.nc", machine=machine)
        assert any("line 6" in w and "stripped" in w for w in analysis["warnings"])
        await rpc.call("subscribe", topics=["job"], machine=machine)
        started = await rpc.call("job.start", machine=machine, file="two.nc")
        assert [w.split(":")[0] for w in started["warnings"]] == ["line 3", "line 6"]
        done = await job_end(rpc, started["job"])
        assert done["state"] == "completed" and done["lines_acked"] == LINES
        assert done["tool_changes"] == []


@pytest.mark.parametrize("machine", MACHINES)
async def test_refuse_refuses_the_file_naming_its_m6_lines(tmp_path: Path, machine: str) -> None:
    async with _daemon(tmp_path, "refuse") as (_, rpc):
        await rpc.call("file.upload", name="two.nc", data=TWO_TOOLS)
        err = await fails(1008, rpc.call("job.start", machine=machine, file="two.nc"))
        assert [p["line"] for p in err.data["problems"]] == [3, 6]
        assert "line 3" in err.message and "line 6" in err.message
        status = await rpc.call("machine.status", machine=machine)
        assert status["job"] is None and status["supervisor"] == "idle"


async def test_pause_refuses_an_m6_whose_tool_is_unknown(paused: tuple[Running, Rpc]) -> None:
    _, rpc = paused
    await rpc.call("file.upload", name="which.nc", data="G0 X1\nM6\nG0 X0\n")
    err = await fails(1008, rpc.call("job.start", machine=G2, file="which.nc"))
    assert err.data["problems"][0]["line"] == 2 and "T word" in err.message


# The sensor at machine X-5 Y-5; a tool of the first length closes it at machine Z-20.
SENSOR = {"x": -5.0, "y": -5.0}
SENSOR_Z = -20.0
PROBED = "G21 G90\nG0 X0 Y0 Z0\nT1 M6\nG0 X1\nG1 X2 F3000\nT2 M6\nG0 Z-5\nG1 X3\nM2\n"


@pytest.mark.parametrize("machine", MACHINES)
async def test_probe_measures_each_tool_and_offsets_the_longer_one(
    tmp_path: Path, machine: str
) -> None:
    probe = {"feed": 600.0, "max_travel": 25.0, "tool_sensor": SENSOR}
    async with _daemon(tmp_path, "probe", probe=probe, safe_z=0.0) as (running, rpc):
        sim = running.daemon.sims[machine]
        sim.tool_sensor(SENSOR["x"], SENSOR["y"], SENSOR_Z)
        job_id = await _start(rpc, machine, "probed.nc", PROBED)

        await _waiting(rpc, machine, job_id, 3)
        await rpc.call("job.tool_change_done", machine=machine)  # the reference: tool 1
        after_first = await rpc.call("machine.status", machine=machine)
        assert after_first["probe"]["ok"] is True
        assert after_first["probe"]["position"]["z"] == pytest.approx(SENSOR_Z, abs=0.01)

        waiting = await _waiting(rpc, machine, job_id, 6, changes=1)
        assert waiting["machine_position"]["x"] == pytest.approx(2.0, abs=0.01)
        sim.tool_length(3.0)  # the operator put in a tool 3 mm longer
        job = await rpc.call("job.tool_change_done", machine=machine)
        assert [c["tool"] for c in job["tool_changes"]] == [1, 2]
        measured = await rpc.call("machine.status", machine=machine)
        assert measured["probe"]["position"]["z"] == pytest.approx(SENSOR_Z + 3.0, abs=0.01)

        done = await job_end(rpc, job_id)
        assert done["state"] == "completed", done
        end = await rpc.call("machine.status", machine=machine)
        # G0 Z-5 under the longer tool's offset: the spindle stays 3 mm higher, and the
        # job's X and feed went on where they were (back over X2, then X3 at its F).
        assert end["machine_position"]["z"] == pytest.approx(-2.0, abs=0.01)
        assert end["machine_position"]["x"] == pytest.approx(3.0, abs=0.01)


async def test_a_measurement_crosses_no_lower_than_the_job_left_the_tool(
    tmp_path: Path,
) -> None:
    """The job lifts to Z0 before its M6; the machine's safe_z is -10. The measurement
    goes across to the sensor at Z0, and back at Z0: it never drops to the safe height
    first, under the job's own clearance."""
    probe = {"feed": 600.0, "max_travel": 25.0, "tool_sensor": SENSOR}
    job = "G21 G90\nG0 X0 Y0 Z0\nT1 M6\nG0 X1\nM2\n"
    async with _daemon(tmp_path, "probe", probe=probe, safe_z=-10.0) as (running, rpc):
        sim = running.daemon.sims[G2]
        sim.tool_sensor(SENSOR["x"], SENSOR["y"], SENSOR_Z)
        job_id = await _start(rpc, G2, "lifted.nc", job)
        await _waiting(rpc, G2, job_id, 3)
        await rpc.call("job.tool_change_done", machine=G2)
        assert (await job_end(rpc, job_id))["state"] == "completed"
        sent = _unnumbered(lines_sent(running, G2))
        assert b"G53 G0 Z0" in sent and b"G53 G0 Z-10" not in sent, sent


@pytest.mark.parametrize("machine", MACHINES)
async def test_probe_on_an_unhomed_machine_without_safe_z_moves_nothing(
    tmp_path: Path, machine: str
) -> None:
    """The way to the sensor starts at the safe height. Unhomed, the Z travel's top is
    no place (machine coordinates count from where the board was switched on) and
    `G53 G0 Z<top>` could go down, or into the end stop: without `safe_z` the answer
    is refused, nothing is written, and the job still waits for it."""
    probe = {"feed": 600.0, "max_travel": 25.0, "tool_sensor": SENSOR}
    async with _daemon(tmp_path, "probe", probe=probe) as (running, rpc):
        sim = running.daemon.sims[machine]
        sim.tool_sensor(SENSOR["x"], SENSOR["y"], SENSOR_Z)
        job_id = await _start(rpc, machine, "probed.nc", PROBED)
        before = await _waiting(rpc, machine, job_id, 3)
        with pytest.raises(RpcFailure) as refused:
            await rpc.call("job.tool_change_done", machine=machine)
        assert "safe_z" in refused.value.message and "home" in refused.value.message
        now = await rpc.call("machine.status", machine=machine)
        assert now["machine_position"] == before["machine_position"]
        assert now["tool_change"] == {"tool": 1, "line": 3}
        assert (await rpc.call("job.get", job=job_id))["state"] == "paused"
        await rpc.call("job.cancel", machine=machine)


@pytest.mark.parametrize("machine", MACHINES)
async def test_probe_that_misses_the_sensor_stops_in_the_boards_alarm(
    tmp_path: Path, machine: str
) -> None:
    """G38.2 that never touches is an ALARM on both firmwares (cycle_probing.cpp,
    grbl's ALARM:5): the job ends failed there, resumable, the board where it stopped."""
    probe = {"feed": 600.0, "max_travel": 5.0, "tool_sensor": SENSOR}
    async with _daemon(tmp_path, "probe", probe=probe, safe_z=0.0) as (running, rpc):
        running.daemon.sims[machine].tool_sensor(SENSOR["x"], SENSOR["y"], SENSOR_Z)
        job_id = await _start(rpc, machine, "probed.nc", PROBED)
        await _waiting(rpc, machine, job_id, 3)
        await rpc.call("subscribe", topics=["status"], machine=machine)
        # 5 mm of travel from Z0 never reaches the sensor's Z-20.
        with pytest.raises(RpcFailure) as err:
            await rpc.call("job.tool_change_done", machine=machine)
        assert err.value.code in (204, 1005), err.value
        ended = await job_end(rpc, job_id)
        assert ended["state"] == "failed" and ended["tool_changes"] == []
        # The refusal and the job's end may come before the board's report after its
        # alarm (grbl: ALARM:5, then the report the session asks for): wait for it.
        await rpc.notification(
            lambda n: (
                n["method"] == "status"
                and n["params"]["snapshot"]["state"]["name"] == "ALARM"
                and n["params"]["snapshot"]["machine_position"]["z"] < -1
            )
        )
        status = await rpc.call("machine.status", machine=machine)  # the job has ended
        assert status["state"]["name"] == "ALARM" and status["tool_change"] is None
        assert status["machine_position"]["z"] == pytest.approx(-5.0, abs=0.01)
        assert status["machine_position"]["x"] == pytest.approx(SENSOR["x"], abs=0.01)


async def test_the_operator_cannot_move_the_machine_while_a_tool_is_measured(
    tmp_path: Path,
) -> None:
    probe = {"feed": 600.0, "max_travel": 25.0, "tool_sensor": SENSOR}
    async with _daemon(tmp_path, "probe", probe=probe, safe_z=0.0) as (running, rpc):
        sim = running.daemon.sims[G2]
        assert isinstance(sim, SimController)
        sim.tool_sensor(SENSOR["x"], SENSOR["y"], SENSOR_Z)
        job_id = await _start(rpc, G2, "probed.nc", PROBED)
        await _waiting(rpc, G2, job_id, 3)
        await rpc.call("subscribe", topics=["status"], machine=G2)
        answering = asyncio.create_task(rpc.call("job.tool_change_done", machine=G2))
        # On its way to the sensor: the board stops reading, so the measuring stays
        # under way for as long as the test needs.
        await rpc.notification(
            lambda n: (
                n["method"] == "status" and n["params"]["snapshot"]["machine_position"]["x"] < -1
            )
        )
        sim.stop_reading()
        try:
            await fails(1003, rpc.call("machine.send", machine=G2, line="G0 X0"))
            await fails(1003, rpc.call("machine.jog", machine=G2, axes={"x": 1.0}, feed=600))
            await fails(1003, rpc.call("job.tool_change_done", machine=G2))
        finally:
            sim.resume_reading()
        job = await answering
        assert [c["tool"] for c in job["tool_changes"]] == [1]


# The spindle on at 8000 rpm when the job reaches its M6 (line 5).
SPINNING = "G21 G90\nG0 X0 Y0 Z0\nM3 S8000\nG1 X1 F3000\nT2 M6\nG0 X2\nM5\nM2\n"


def _spindle_of(running: Running, machine: str) -> str:
    """The spindle as the simulated board's interpreter holds it (M3, M4 or M5)."""
    sim = running.daemon.sims[machine]
    if isinstance(sim, SimController):
        return str(sim._board.interp.spindle)
    return str(sim.board.modal.spindle)  # type: ignore[attr-defined]


def _unnumbered(sent: list[bytes]) -> list[bytes]:
    return [re.sub(rb"^N[0-9]+ *", b"", line) for line in sent]


@pytest.mark.parametrize("machine", MACHINES)
async def test_the_spindle_stops_for_the_change_and_comes_back_as_the_job_had_it(
    tmp_path: Path, machine: str
) -> None:
    async with _daemon(tmp_path, "pause", spindle_dwell=0.05) as (running, rpc):
        if machine == GRBL:  # the simulated grbl is a laser ($32=1): make it a mill
            await rpc.call("settings.set", machine=machine, values={"32": 0})
            await rpc.call("settings.get", machine=machine, keys=["32"])  # `$$`: read again
            status = await rpc.call("machine.status", machine=machine)
            assert status["laser_mode"] is False
        job_id = await _start(rpc, machine, "spin.nc", SPINNING)
        await _waiting(rpc, machine, job_id, 5)
        # The operator is told of the change only once the spindle is off.
        assert _spindle_of(running, machine) == "M5"
        sent = _unnumbered(lines_sent(running, machine))
        assert [line for line in sent if line[:2] in (b"M3", b"M4", b"M5")] == [
            b"M3 S8000",
            b"M5",
        ], sent
        before = len(sent)
        await rpc.call("job.tool_change_done", machine=machine)
        done = await job_end(rpc, job_id)
        assert done["state"] == "completed", done
        # (grbl: the `$G` after each line of the host's own, which reads its modes back)
        after = [ln for ln in _unnumbered(lines_sent(running, machine))[before:] if ln != b"$G"]
        # Back on as it was, the machine's dwell for it to reach its speed, then the job.
        assert after[:2] == [b"M3 S8000", b"G4 P0.05"], after
        assert after.index(b"G0 X2") > 1 and _spindle_of(running, machine) == "M5"


def _modes_of(running: Running, machine: str) -> tuple[float | None, int, int]:
    """The motion mode, plane and coordinate system (1 = G54) the simulated board holds."""
    sim = running.daemon.sims[machine]
    if isinstance(sim, SimController):
        interp = sim._board.interp
        return interp.motion, interp.plane, interp.coord
    modal = sim.board.modal  # type: ignore[attr-defined]
    return modal.motion, modal.plane, modal.coord + 1


# G18 and G55 in force, G1 modal: line 7's bare `X3` must run as a feed, in G55, on G18.
MODAL = "G21 G90 G18 G55\nG0 X0 Y0 Z0\nT1 M6\nG1 X1 F3000\nX2\nT2 M6\nX3\n"


@pytest.mark.parametrize("machine", MACHINES)
async def test_a_measured_tool_change_gives_the_job_its_modes_back(
    tmp_path: Path, machine: str
) -> None:
    """The measuring ends in `G53 G0` moves: without the program's G1 put back, its
    next bare `X3` would be a rapid."""
    probe = {"feed": 600.0, "max_travel": 25.0, "tool_sensor": SENSOR}
    async with _daemon(tmp_path, "probe", probe=probe, safe_z=0.0) as (running, rpc):
        running.daemon.sims[machine].tool_sensor(SENSOR["x"], SENSOR["y"], SENSOR_Z)
        job_id = await _start(rpc, machine, "modal.nc", MODAL)
        await _waiting(rpc, machine, job_id, 3)
        await rpc.call("job.tool_change_done", machine=machine)
        await _waiting(rpc, machine, job_id, 6, changes=1)
        before = len(lines_sent(running, machine))
        await rpc.call("job.tool_change_done", machine=machine)
        done = await job_end(rpc, job_id)
        assert done["state"] == "completed", done
        sent = _unnumbered(lines_sent(running, machine))[before:]
        assert b"G21 G90 G18 G55 G1 F3000" in sent, sent
        assert _modes_of(running, machine) == (1, 18, 2)  # G1, G18, G55 as the job left them
        end = await rpc.call("machine.status", machine=machine)
        assert end["machine_position"]["x"] == pytest.approx(3.0, abs=0.01)


# Relative moves: after the change, `G0 X1` goes one more millimetre, to X2.
RELATIVE = "G21 G91\nG0 X1\nT2 M6\nG0 X1\n"


@pytest.mark.parametrize("machine", MACHINES)
async def test_the_operators_jog_and_lines_at_a_pause_leave_the_jobs_modes_as_they_were(
    paused: tuple[Running, Rpc], machine: str
) -> None:
    """A g2core jog is G-code (`G91 G1 .. F..`, then `G90`), and the operator may send
    `G20`: the job's G21 G91 are put back before its next line."""
    _, rpc = paused
    job_id = await _start(rpc, machine, "relative.nc", RELATIVE)
    await _waiting(rpc, machine, job_id, 3)
    await rpc.call("subscribe", topics=["status"], machine=machine)
    await rpc.call("machine.jog", machine=machine, axes={"z": 1.0}, feed=600)
    await rpc.notification(lambda n: n["method"] == "status" and _rests_at(n, z=1.0))
    await rpc.call("machine.send", machine=machine, line="G20")
    await rpc.call("job.tool_change_done", machine=machine)
    done = await job_end(rpc, job_id)
    assert done["state"] == "completed", done
    end = await rpc.call("machine.status", machine=machine)
    assert end["units"] == "mm"
    assert end["machine_position"]["x"] == pytest.approx(2.0, abs=0.01)
    assert end["machine_position"]["z"] == pytest.approx(1.0, abs=0.01)


@pytest.mark.parametrize(
    ("m6_line", "back", "spindle"),
    [
        ("T2 M5 M6", [], "M5"),  # the program stops it with the change: never spun up
        ("T2 M6 M4 S900", [b"M4 S900", b"G4 P0.05"], "M4"),  # not clockwise first
    ],
)
async def test_a_spindle_word_on_the_m6_line_is_the_spindle_the_answer_restores(
    tmp_path: Path, m6_line: str, back: list[bytes], spindle: str
) -> None:
    """The spindle comes back as the program has it once its M6 line runs, that line's
    own M3/M4/M5 and S first: `T2 M5 M6` would otherwise spin the new tool up for the
    dwell only to stop it, and `T2 M6 M4` run it clockwise, then reverse it."""
    program = f"G21 G90\nG0 X0 Y0 Z5\nM3 S8000\nG1 X1 F600\n{m6_line}\nG0 X2\n"
    async with _daemon(tmp_path, "pause", spindle_dwell=0.05) as (running, rpc):
        job_id = await _start(rpc, G2, "spin.nc", program)
        await _waiting(rpc, G2, job_id, 5)
        assert _spindle_of(running, G2) == "M5"  # off while the operator's hands are there
        before = len(lines_sent(running, G2))
        await rpc.call("job.tool_change_done", machine=G2)
        done = await job_end(rpc, job_id)
        assert done["state"] == "completed", done
        after = _unnumbered(lines_sent(running, G2))[before:]
        restored = after[: after.index(next(ln for ln in after if b"M6" in ln))]
        assert [ln for ln in restored if ln[:2] in (b"M3", b"M4", b"G4")] == back, after
        assert _spindle_of(running, G2) == spindle
