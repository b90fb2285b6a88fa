"""The operator's operations and the frame's checks: what the operator would notice that
test_operations.py, test_power.py and test_laser_power_bound.py leave open (a hand-run
mutation campaign on hostd/machine/operations.py, machine_operations.py, preflight.py
and guard.py found each of these unpinned). One is not a gap but a fault the campaign
came across, now fixed: `machine.goto_zero` drove Z *down* to `safe_z` before it crossed
when the tool stood above it (test_goto_zero_from_above_the_safe_height_crosses_where_the_
tool_is), and in G20 went to `safe_z` inches.

A real daemon with a simulated g2core (sim1) and a simulated grbl (sim2) on real ptys,
reached through the real socket.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from hostd.machine import jobfile, machine_operations, preflight
from hostd.protocol.states import MachineState
from hostd.sim import SimController
from hostd.sim.grbl.controller import GrblSimController
from tests.daemon.conftest import G2, GRBL, Rpc, Running, running_daemon
from tests.daemon.test_api import fails, job_end
from tests.daemon.test_guard import reached
from tests.daemon.test_jog_bounds_in_inches import ABSURD
from tests.daemon.test_operations import jog_to, lines_sent
from tests.daemon.test_power import BOXED, grbl_board, grbl_sim, traced
from tests.daemon.test_resume import _g2_state, with_line_numbers
from tests.daemon.test_toolchange import RELATIVE, _rests_at, _start, _waiting

pytestmark = pytest.mark.asyncio

# The program rises to work Z20 before it cuts at Z-1 (test_power.py's clearance file).
CLEARANCE = "G21 G90\nG0 Z20\nG0 X12 Y7\nG1 Z-1 F100\nG1 X30 Y25 F800\nG0 Z20\n"


@contextlib.asynccontextmanager
async def _daemon(
    tmp_path: Path, g2: dict[str, Any] | None = None, grbl: dict[str, Any] | None = None
) -> AsyncIterator[tuple[Running, Rpc]]:
    """sim1 (g2core, its config `g2`) and sim2 (grbl, `grbl`) idle, a client told of jobs."""
    per_machine = [g2 or {}, {"dialect": "grbl", **(grbl or {})}]
    async with running_daemon(tmp_path, machines=2, per_machine=per_machine) as hostd:
        rpc = await hostd.client()
        try:
            await rpc.call("subscribe", topics=["job"])
            for machine in (G2, GRBL):
                await hostd.idle(rpc, machine)
            yield hostd, rpc
        finally:
            await rpc.close()


def g2_sim(hostd: Running) -> SimController:
    sim = hostd.daemon.sims[G2]
    assert isinstance(sim, SimController)
    return sim


async def test_a_g2core_homing_cycle_that_fails_is_an_error_and_the_machine_stays_unhomed(
    tmp_path: Path,
) -> None:
    """g2core answers the `G28.2` with ok as the cycle starts and reports the failure
    apart (status 240, "X axis ..."): `machine.home` is 1005 with the board's message,
    not `{}`, and the snapshot still says not homed. An operator told "homed" would trust
    machine coordinates that count from wherever the board was switched on."""
    async with _daemon(tmp_path) as (hostd, rpc):
        g2_sim(hostd).fail_homing("x", 246)
        err = await fails(1005, rpc.call("machine.home", machine=G2))
        assert "X axis" in err.message, err.message
        assert (await rpc.call("machine.status", machine=G2))["homed"] is False


async def test_a_g2core_homing_cycle_stopped_by_an_alarm_is_an_error(tmp_path: Path) -> None:
    """A limit switch trips while the board homes: the cycle ends in ALARM, not homed.
    `machine.home` says so (1005, "ended in ALARM") rather than `{}`: an operator told
    the machine is homed would jog and frame by a position the board never found."""
    async with _daemon(tmp_path) as (hostd, rpc):
        await jog_to(hostd, rpc, G2, {"x": 250, "y": 250})
        sim = g2_sim(hostd)
        homing = asyncio.ensure_future(rpc.call("machine.home", machine=G2))
        await sim.wait_for(lambda: sim.state is MachineState.HOMING)
        sim.limit_switch("x")
        err = await fails(1005, homing)
        assert "ALARM" in err.message, err.message
        snap = await rpc.call("machine.status", machine=G2)
        assert snap["state"]["name"] == "ALARM" and snap["homed"] is not True


# -- frame -------------------------------------------------------------------


async def frame(hostd: Running, rpc: Rpc, machine: str, text: str, **params: Any) -> list[Any]:
    """Frame `text` on `machine` to its end (completed); the moves the board made for it."""
    (hostd.jobs / "part.gcode").write_text(text)
    before = len(traced(hostd, machine))
    job = await rpc.call("machine.frame", machine=machine, file="part.gcode", **params)
    ended = await job_end(rpc, job["job"])
    assert ended["state"] == "completed", ended
    return traced(hostd, machine)[before:]


async def test_a_laser_frames_at_its_focus_height_even_with_a_safe_z(tmp_path: Path) -> None:
    """A laser traces at its current Z, its focus: a `safe_z` in its config (for its
    resumes) does not lift the head to 10 mm before the frame, which would trace the box
    out of focus and leave the head there."""
    async with _daemon(tmp_path, g2={"laser": True, "safe_z": 10.0}) as (hostd, rpc):
        moves = await frame(hostd, rpc, G2, BOXED)
        assert {round(m.move.target["z"], 3) for m in moves} == {0.0}
        assert not any(line.startswith(b"G53") for line in lines_sent(hostd, G2))


async def test_a_mills_frame_climbs_to_the_programs_top_in_machine_coordinates(
    tmp_path: Path,
) -> None:
    """Work Z0 set 10 mm above machine Z0: the program's clearance (work Z20) is machine
    Z30, and the frame crosses there (`G53 G0 Z30`), not at machine Z20 (the program's
    number taken for a machine height, 10 mm lower than the program ever crosses)."""
    async with _daemon(tmp_path, g2={"safe_z": 5.0}) as (hostd, rpc):
        await jog_to(hostd, rpc, G2, {"z": 10})
        await rpc.call("machine.zero", machine=G2, axes={"z": 0})
        moves = await frame(hostd, rpc, G2, CLEARANCE)
        assert any(line.endswith(b"G53 G0 Z30") for line in lines_sent(hostd, G2))
        assert {round(m.move.target["z"], 3) for m in moves[-5:]} == {30.0}
        assert min(m.move.target["z"] for m in moves) >= 10.0 - 1e-3  # never down


async def test_a_mill_above_its_safe_height_frames_there_and_never_goes_down(
    tmp_path: Path,
) -> None:
    """The tool stands at Z20, above `safe_z` (5): the frame traces at Z20. Z never goes
    down to the safe height, which may be below the clamps the operator cleared by hand."""
    async with _daemon(tmp_path, g2={"safe_z": 5.0}) as (hostd, rpc):
        await jog_to(hostd, rpc, G2, {"z": 20})
        before = len(lines_sent(hostd, G2))
        moves = await frame(hostd, rpc, G2, BOXED)
        assert {round(m.move.target["z"], 3) for m in moves} == {20.0}
        assert not any(line.startswith(b"G53") for line in lines_sent(hostd, G2)[before:])


async def test_a_spindle_left_running_is_stopped_before_the_frame_moves(tmp_path: Path) -> None:
    """The operator left the spindle on (`machine.spindle` cw): the frame's first line
    stops it, so the box is walked with the spindle still, not with a turning cutter."""
    async with _daemon(tmp_path, g2={"safe_z": 5.0}) as (hostd, rpc):
        assert await rpc.call("machine.spindle", machine=G2, state="cw", speed=1000) == {}
        moves = await frame(hostd, rpc, G2, BOXED)
        assert moves and not any(m.cutting for m in moves), [m.move for m in moves]


async def test_a_lasers_frame_at_power_ends_with_the_beam_off(tmp_path: Path) -> None:
    """A frame at 2 % burns along the sides; its last line turns the beam off (`M5`), so
    the next move the operator makes does not burn at the frame's power."""
    async with _daemon(tmp_path, grbl={"laser": True}) as (hostd, rpc):
        moves = await frame(hostd, rpc, GRBL, BOXED, power=2)
        assert any(m.cutting for m in moves)
        assert grbl_board(hostd).modal.spindle == "M5"


async def test_a_frame_traces_millimetres_and_gives_back_g20_and_g91(tmp_path: Path) -> None:
    """The operator left the board in G20 G91: the frame traces the program's box in mm,
    absolute (12 mm, not 12 inches, and not 12 mm further each side), at the feed asked,
    and the board is back in G20 G91 afterwards, as the operator's next lines expect."""
    async with _daemon(tmp_path, g2={"safe_z": 5.0}) as (hostd, rpc):
        await rpc.call("subscribe", topics=["status"], machine=G2)
        await rpc.call("machine.send", machine=G2, line="G20 G91")
        await rpc.notification(
            lambda n: (
                n["method"] == "status"
                and n["params"]["snapshot"]["units"] == "in"
                and n["params"]["snapshot"]["distance"] == "G91"
            )
        )
        moves = await frame(hostd, rpc, G2, BOXED, feed=2000)
        corners = [(round(m.move.target["x"], 3), round(m.move.target["y"], 3)) for m in moves]
        assert corners[-5:] == [(12, 7), (32.071, 7), (32.071, 25), (12, 25), (12, 7)]
        assert any(line.endswith(b" F2000") for line in lines_sent(hostd, G2))
        board = _g2_state(g2_sim(hostd))
        assert board["metric"] is False and board["absolute"] is False, board


async def test_a_frame_whose_box_leaves_the_travel_in_y_is_refused(tmp_path: Path) -> None:
    """The box runs to Y350 on a homed machine whose Y travels 300 mm: file.analyze says
    so beforehand, and the frame is refused (1008) with nothing moved."""
    async with _daemon(tmp_path) as (hostd, rpc):
        assert await rpc.call("machine.home", machine=G2) == {}
        (hostd.jobs / "tall.gcode").write_text("G21 G90\nG0 X12 Y7\nG1 X30 Y350 F800\n")
        found = await rpc.call("file.analyze", machine=G2, file="tall.gcode")
        assert [text[0] for text in found["frame_beyond_travel"]] == ["Y"], found
        before = len(traced(hostd, G2))
        err = await fails(1008, rpc.call("machine.frame", machine=G2, file="tall.gcode"))
        assert err.data["beyond_travel"] == found["frame_beyond_travel"]
        assert len(traced(hostd, G2)) == before


async def test_a_frame_with_any_power_on_a_mill_is_refused(tmp_path: Path) -> None:
    """grbl out of laser mode (`$32=0`) is a mill: a frame asked at 0.5 % is refused as
    not a laser (-32602), however little the power, and nothing moves: on a mill the
    "beam" is the spindle, turning as the box is walked."""
    async with _daemon(tmp_path, grbl={"safe_z": 0.0}) as (hostd, rpc):
        await rpc.call("settings.set", machine=GRBL, values={"32": 0})
        await hostd.idle(rpc, GRBL)
        assert (await rpc.call("machine.status", machine=GRBL))["laser_mode"] is False
        (hostd.jobs / "part.gcode").write_text(BOXED)
        before = len(traced(hostd, GRBL))
        frame = rpc.call("machine.frame", machine=GRBL, file="part.gcode", power=0.5)
        err = await fails(-32602, frame)
        assert "not a laser (set laser = true" in err.message, err.message
        assert len(traced(hostd, GRBL)) == before


async def test_a_file_that_moves_along_x_alone_has_no_box_to_frame(tmp_path: Path) -> None:
    """A program that moves only in X (no Y word anywhere): refused as having no X and Y
    box (-32602), not a daemon error, and nothing moves."""
    async with _daemon(tmp_path, grbl={"laser": True}) as (hostd, rpc):
        (hostd.jobs / "line.gcode").write_text("G21 G90\nG1 X10 F100\n")
        before = len(traced(hostd, GRBL))
        err = await fails(-32602, rpc.call("machine.frame", machine=GRBL, file="line.gcode"))
        assert "no X and Y" in err.message
        assert len(traced(hostd, GRBL)) == before


# -- jog -----------------------------------------------------------------------


async def test_a_jog_alone_at_a_tool_change_gives_the_job_back_its_relative_mode(
    tmp_path: Path,
) -> None:
    """A g2core jog is `G91 G1 .. F..` then `G90`. The operator only jogs at the pause
    (no line of their own): the program's G91 is still put back before its next line, so
    its `G0 X1` after the change goes one more millimetre (to X2), not to X1."""
    async with _daemon(tmp_path, g2={"tool_change": "pause"}) as (_, rpc):
        job_id = await _start(rpc, G2, "relative.nc", RELATIVE)
        await _waiting(rpc, G2, job_id, 3)
        await rpc.call("subscribe", topics=["status"], machine=G2)
        await rpc.call("machine.jog", machine=G2, axes={"z": 1.0}, feed=600)
        await rpc.notification(lambda n: n["method"] == "status" and _rests_at(n, z=1.0))
        await rpc.call("job.tool_change_done", machine=G2)
        assert (await job_end(rpc, job_id))["state"] == "completed"
        end = await rpc.call("machine.status", machine=G2)
        assert end["machine_position"]["x"] == pytest.approx(2.0, abs=0.01)


async def test_a_grbl_jog_a_fraction_past_its_travel_is_refused(tmp_path: Path) -> None:
    """grbl's X travels 200 mm (`$130`): a jog of 200.4 mm is longer than the axis, and
    refused (-32602, absurd-jog) with nothing sent, not rounded to 200 and let through."""
    async with _daemon(tmp_path) as (hostd, rpc):
        jog = rpc.call("machine.jog", machine=GRBL, axes={"x": -200.4}, feed=600)
        assert (await fails(-32602, jog)).data == ABSURD
        assert not reached(hostd, GRBL, "X-200.4")


async def test_a_grbl_jog_sent_as_a_line_in_inches_is_bounded_in_inches(tmp_path: Path) -> None:
    """After a G20, `machine.send` of `$J=G91 X10 F10` is a 10-inch jog (254 mm), longer
    than the 200 mm grbl's X travels: refused as absurd (-32602) with nothing sent, as
    `machine.jog` refuses it; read in mm it would have gone to the board."""
    async with _daemon(tmp_path) as (hostd, rpc):
        await rpc.call("subscribe", topics=["status"], machine=GRBL)
        await rpc.call("machine.send", machine=GRBL, line="G20")
        await rpc.notification(
            lambda n: n["method"] == "status" and n["params"]["snapshot"]["units"] == "in"
        )
        send = rpc.call("machine.send", machine=GRBL, line="$J=G91 X10 F10")
        assert (await fails(-32602, send)).data == ABSURD
        assert not reached(hostd, GRBL, "$J=G91 X10")


# -- laser test-fire -----------------------------------------------------------


async def test_a_laser_test_whose_beam_off_is_not_answered_ends_in_a_reset(
    tmp_path: Path,
) -> None:
    """Held mid-burn (`machine.feedhold`) and left held, the test-fire's `M5` is never
    answered: once the dwell and 5 s more have passed the daemon resets the board (0x18,
    every firmware's way to stop the spindle) instead of leaving it holding a beam line
    that a cycle start would fire again. The call fails saying the board did not answer."""
    async with _daemon(tmp_path, grbl={"laser": True}) as (hostd, rpc):
        sim, board = grbl_sim(hostd), grbl_board(hostd)
        firing = asyncio.ensure_future(
            rpc.call("machine.laser_test", machine=GRBL, power=5, duration_s=1.0)
        )
        await sim.wait_for(lambda: board.beam_power() > 0)
        held = len(sim.received)
        await rpc.call("machine.feedhold", machine=GRBL)
        await fails(1006, firing)
        assert any(b"\x18" in r.data for r in list(sim.received)[held:])
        await sim.wait_for(lambda: board.modal.spindle == "M5" and not sim.state.startswith("Hold"))
        assert board.beam_power() == 0.0


async def test_a_laser_test_of_two_seconds_the_bound_itself_is_taken(tmp_path: Path) -> None:
    """api.md: `duration_s` at most 2. A test-fire of exactly 2 s fires and ends off; it
    is not refused as over the bound."""
    async with _daemon(tmp_path, grbl={"laser": True}) as (hostd, rpc):
        board = grbl_board(hostd)
        assert await rpc.call("machine.laser_test", machine=GRBL, power=5, duration_s=2) == {}
        assert any(power > 0 for _, power in board.beam)
        assert board.beam_power() == 0.0
        assert b"G4 P2" in lines_sent(hostd, GRBL)


async def grbl_alarm_after_a_hard_limit(hostd: Running, rpc: Rpc) -> GrblSimController:
    """A hard limit tripped and was reset: grbl, with homing on, stays in ALARM until
    homed or unlocked. Its sim, the board in that ALARM; `rpc` is told its status."""
    # Homing switches and hard limits on, as the board's owner would set them.
    await rpc.call("settings.set", machine=GRBL, values={"22": 1, "21": 1})
    await hostd.idle(rpc, GRBL)
    await rpc.call("subscribe", topics=["status"], machine=GRBL)
    sim = grbl_sim(hostd)
    sim.limit_switch("x")
    await rpc.notification(
        lambda n: n["method"] == "status" and n["params"]["snapshot"]["state"]["name"] == "ALARM"
    )
    sim.limit_switch("x", active=False)
    await rpc.call("machine.reset", machine=GRBL)
    assert (await rpc.call("machine.status", machine=GRBL))["state"]["name"] == "ALARM"
    return sim


async def test_a_laser_test_in_an_alarm_is_its_code_and_touches_nothing(tmp_path: Path) -> None:
    """A test-fire in a grbl ALARM is refused with the lockout's code (204) before any
    line of it is written: no beam line, and no reset of the board either (a reset runs
    its startup blocks, and ends the alarm the operator must read)."""
    async with _daemon(tmp_path, grbl={"laser": True}) as (hostd, rpc):
        sim = await grbl_alarm_after_a_hard_limit(hostd, rpc)
        before = len(sim.received)
        await fails(204, rpc.call("machine.laser_test", machine=GRBL, power=5, duration_s=0.5))
        written = b"".join(r.data for r in list(sim.received)[before:])
        assert b"M3" not in written and b"\x18" not in written, written
        assert [p for _, p in grbl_board(hostd).beam if p > 0] == []


async def test_a_laser_test_on_a_board_whose_full_power_is_zero_is_refused(
    tmp_path: Path,
) -> None:
    """`$30=0`: no full-power S to take a percent of. The test-fire is refused (1005,
    saying the board gave no spindle maximum) instead of answering `{}` for a beam that
    never came on, which the operator would take for a dead tube."""
    async with _daemon(tmp_path, grbl={"laser": True}) as (hostd, rpc):
        await rpc.call("settings.set", machine=GRBL, values={"30": 0})
        await hostd.idle(rpc, GRBL)
        err = await fails(
            1005, rpc.call("machine.laser_test", machine=GRBL, power=5, duration_s=0.2)
        )
        assert "spindle maximum" in err.message
        assert not any(b"M3" in line for line in lines_sent(hostd, GRBL))


# -- go to zero ----------------------------------------------------------------


async def test_goto_zero_from_above_the_safe_height_crosses_where_the_tool_is(
    tmp_path: Path,
) -> None:
    """The operator raised the tool to Z20 to clear a clamp; `safe_z` is 5. Going to
    zero must not first drive Z *down* to 5 and cross there: `safe_z` is "the height the
    tool goes up to before it crosses" (operations.md), and the frame and the tool change
    never go down before crossing. X and Y are crossed at Z20, then Z goes to zero."""
    async with _daemon(tmp_path, g2={"safe_z": 5.0}) as (hostd, rpc):
        await jog_to(hostd, rpc, G2, {"x": 40, "y": 30, "z": 20})
        before = len(traced(hostd, G2))
        assert await rpc.call("machine.goto_zero", machine=G2) == {}
        moves = traced(hostd, G2)[before:]
        crossing = [m for m in moves if m.move.target["x"] != m.start["x"]]
        assert crossing and all(m.start["z"] >= 20 - 1e-3 for m in crossing), [
            (m.start, m.move.target) for m in moves
        ]
        assert moves[-1].move.target == pytest.approx({"x": 0, "y": 0, "z": 0}, abs=1e-3)


async def test_goto_zero_in_g20_rises_to_the_safe_height_in_millimetres(tmp_path: Path) -> None:
    """`safe_z` is millimetres; a board left in G20 by an inch program reads a `G53 G0
    Z5` as 5 inches (127 mm). The lift goes to 5 mm, written in the board's units, and
    the board stays in G20."""
    async with _daemon(tmp_path, g2={"safe_z": 5.0}) as (hostd, rpc):
        await rpc.call("machine.send", machine=G2, line="G20")
        before = len(traced(hostd, G2))
        assert await rpc.call("machine.goto_zero", machine=G2) == {}
        moves = traced(hostd, G2)[before:]
        top = max(max(m.start["z"], m.move.target["z"]) for m in moves)
        assert top == pytest.approx(5.0, abs=0.005), [(m.start, m.move.target) for m in moves]
        assert (await rpc.call("machine.status", machine=G2))["units"] == "in"


# -- job.start: the travel check and the row -------------------------------------


async def test_a_grbl_never_homed_has_no_travel_check(tmp_path: Path) -> None:
    """grbl cannot say it is homed until it has homed in this session (the snapshot's
    `homed` is null): its machine coordinates count from where it was switched on, so
    neither file.analyze nor job.start checks a program against its travel. A move to
    X50 (outside -200..0 as machine coordinates from here) is not refused by a check
    that means nothing, and file.analyze says the travel was not checked."""
    async with _daemon(tmp_path) as (hostd, rpc):
        assert (await rpc.call("machine.status", machine=GRBL))["homed"] is None
        (hostd.jobs / "right.gcode").write_text("G21 G90\nG0 X50\nG0 X0\n")
        found = await rpc.call("file.analyze", machine=GRBL, file="right.gcode")
        assert found["travel_checked"] is False and found["beyond_travel"] == [], found
        assert found["frame_beyond_travel"] == []
        job = await rpc.call("job.start", machine=GRBL, file="right.gcode")
        assert (await job_end(rpc, job["job"]))["state"] == "completed"


async def test_a_job_run_from_its_first_line_has_no_start_line(tmp_path: Path) -> None:
    """api.md: a job's `start_line` is the first file line of a job started past its
    first line, else null. A whole run's row says null, and has no preamble: the
    history does not show a plain run as a resume."""
    async with _daemon(tmp_path) as (hostd, rpc):
        (hostd.jobs / "whole.gcode").write_text("G21 G90\nG0 X1\nG0 X0\n")
        job = await rpc.call("job.start", machine=G2, file="whole.gcode")
        ended = await job_end(rpc, job["job"])
        assert ended["state"] == "completed" and ended["start_line"] is None, ended
        assert ended["preamble"] is None


async def test_file_analyze_finds_a_line_grbl_cannot_take_once_numbered(tmp_path: Path) -> None:
    """grbl built with line numbers takes lines of 127 bytes with their LF. Line 2 is 124
    bytes: it would fit, but every job line goes with its `N2 ` word, and then it does
    not. file.analyze on that machine lists it (`hostd analyze`, the dashboard's
    warnings), as job.start refuses it: the operator learns it before starting."""
    long = "G1 X1." + "0" * 113 + " F100"
    assert len(long) == 124
    async with running_daemon(tmp_path, dialect="grbl") as hostd:
        rpc = await hostd.client()
        try:
            await hostd.idle(rpc)
            await with_line_numbers(hostd, rpc)
            (hostd.jobs / "long.gcode").write_text(f"G21 G90\n{long}\n")
            found = await rpc.call("file.analyze", machine="sim1", file="long.gcode")
            problems = [(p["line"], p["kind"]) for p in found["problems"]]
            assert problems == [(2, "unsendable")], found
            refused = await fails(1008, rpc.call("job.start", machine="sim1", file="long.gcode"))
            assert refused.data["problems"] == found["problems"]
        finally:
            await rpc.close()


async def test_a_homed_start_reads_the_files_hash_once_and_the_row_keeps_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On a homed machine the travel check hashes the file (its analysis is kept by its
    bytes); the job keeps that hash in its row rather than reading the file again for
    it. A large file is read once less at every start."""
    hashed: list[str] = []

    def counting(file: Any) -> str:
        hashed.append(digest := jobfile.sha256(file))
        return digest

    monkeypatch.setattr(preflight, "sha256", counting)
    monkeypatch.setattr(machine_operations, "sha256", counting)
    async with _daemon(tmp_path) as (hostd, rpc):
        assert await rpc.call("machine.home", machine=G2) == {}
        program = "G21 G90\n" + "".join(f"G1 X{i % 50} Y{i % 40} F900\n" for i in range(300))
        (hostd.jobs / "part.nc").write_text(program)
        await rpc.call("subscribe", topics=["job"], machine=G2)
        job_id = (await rpc.call("job.start", machine=G2, file="part.nc"))["job"]
        await rpc.call("job.cancel", machine=G2)
        row = await rpc.call("job.get", job=job_id)
        assert row["file_sha256"] == hashlib.sha256(program.encode()).hexdigest()
        assert hashed == [row["file_sha256"]]  # once: the check's, kept by the row
