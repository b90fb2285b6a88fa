"""Overrides, laser test-fire, frame and macros (issue 29), on both simulated dialects.

A g2core board and a grbl laser, simulated on real ptys, reached through the
real Unix socket. What a user would notice: an override changed mid-job shows
in the snapshot and the board's own settings; the test-fire's beam always ends
off; a frame traces the job's box with the beam off; a macro runs its lines and
no parameter can smuggle another line in.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio

from hostd.sim import SimController
from hostd.sim.grbl.controller import GrblSimController
from tests.daemon.conftest import Rpc, RpcFailure, Running, running_daemon
from tests.daemon.test_api import fails, job_end
from tests.daemon.test_operations import lines_sent

pytestmark = pytest.mark.asyncio

G2, GRBL = "sim1", "sim2"
MACHINES = (G2, GRBL)
# Long enough to be under way when the override is asked (the sims run 10x real speed).
LONG_JOB = "G21 G90\nG1 X0 Y0 F600\n" + "".join(
    f"G1 X{10 + (i % 2) * 10} Y{i % 7} F600\n" for i in range(60)
)


MACROS = [
    {
        "name": "corner",
        "text": "G21 G90 (to a corner)\nG0 X{x} Y{y}\n\nG4 P{wait}",
        "params": {
            "x": {"min": 0, "max": 40},
            "y": {"min": 0, "max": 40, "default": 3},
            "wait": {"min": 0, "max": 1, "default": 0},
        },
    },
    {"name": "wipe", "text": "$RST=*"},  # a maintenance command: never through a macro
]


@pytest_asyncio.fixture
async def both(tmp_path: Path) -> AsyncIterator[tuple[Running, Rpc]]:
    async with running_daemon(
        tmp_path,
        machines=2,
        per_machine=[{"macros": MACROS}, {"dialect": "grbl", "laser": True, "macros": MACROS}],
    ) as d:
        client = await d.client()
        await client.call("subscribe", topics=["job", "status"])
        for machine in MACHINES:
            await d.idle(client, machine)
        yield d, client
        await client.close()


def g2_sim(hostd: Running) -> SimController:
    sim = hostd.daemon.sims[G2]
    assert isinstance(sim, SimController)
    return sim


async def overrides_shown(rpc: Rpc, machine: str, want: dict[str, float]) -> None:
    await rpc.notification(
        lambda n: (
            n["method"] == "status"
            and n["params"]["machine"] == machine
            and n["params"]["snapshot"]["overrides"] is not None
            and all(n["params"]["snapshot"]["overrides"].get(k) == v for k, v in want.items())
        )
    )


async def test_g2core_knows_its_overrides_from_the_start(both: tuple[Running, Rpc]) -> None:
    _, rpc = both
    snap = await rpc.call("machine.status", machine=G2)
    assert snap["overrides"] == {"feed": 100.0, "rapid": 100.0, "spindle": 100.0}


@pytest.mark.parametrize("machine", MACHINES)
async def test_an_override_changed_mid_job_shows_in_the_snapshot(
    both: tuple[Running, Rpc], machine: str
) -> None:
    hostd, rpc = both
    (hostd.jobs / "long.gcode").write_text(LONG_JOB)
    job = await rpc.call("job.start", machine=machine, file="long.gcode")
    await rpc.notification(
        lambda n: (
            n["method"] == "status"
            and n["params"]["machine"] == machine
            and n["params"]["snapshot"]["state"]["name"] == "RUN"
        )
    )
    got = await rpc.call("machine.override", machine=machine, feed=150, spindle=80)
    assert got["feed"] == 150 and got["spindle"] == 80
    await overrides_shown(rpc, machine, {"feed": 150, "spindle": 80})
    snap = await rpc.call("machine.status", machine=machine)
    assert snap["job"]["state"] == "running"  # the job went on under the override
    if machine == G2:
        board = g2_sim(hostd)._board.settings
        assert board.override("feed") == pytest.approx(1.5)
        assert board.override("spindle") == pytest.approx(0.8)
    await rpc.call("job.cancel", machine=machine)
    await job_end(rpc, job["job"])


async def test_g2core_refuses_an_override_its_firmware_would_refuse(
    both: tuple[Running, Rpc],
) -> None:
    hostd, rpc = both
    err = await fails(-32602, rpc.call("machine.override", machine=G2, rapid=150))
    assert "5 to 100" in err.message
    assert g2_sim(hostd)._board.settings.override("rapid") == 1.0
    got = await rpc.call("machine.override", machine=G2, rapid=25)
    assert got["rapid"] == 25


async def test_an_override_in_a_lockout_is_its_code_and_sends_nothing(
    both: tuple[Running, Rpc],
) -> None:
    hostd, rpc = both
    await rpc.call("machine.alarm", machine=G2)
    await rpc.notification(
        lambda n: (
            n["method"] == "status"
            and n["params"]["machine"] == G2
            and n["params"]["snapshot"]["state"]["name"] == "ALARM"
        )
    )
    await fails(204, rpc.call("machine.override", machine=G2, feed=120))
    assert not any(b'"fro":1.2' in r.data for r in g2_sim(hostd).received)
    await rpc.call("machine.clear", machine=G2)
    got = await rpc.call("machine.override", machine=G2, feed=120)
    assert got["feed"] == 120


async def test_a_program_end_puts_g2cores_feed_override_back(both: tuple[Running, Rpc]) -> None:
    _, rpc = both
    await rpc.call("machine.override", machine=G2, feed=120)
    await rpc.call("machine.send", machine=G2, line="M30")
    await overrides_shown(rpc, G2, {"feed": 100})


def traced(hostd: Running, machine: str) -> list[Any]:
    """The moves the simulated board made (as tests/daemon/test_resume_safety.py reads them)."""
    sim = hostd.daemon.sims[machine]
    record = sim._board.traversed if isinstance(sim, SimController) else sim.board.traversed
    return list(record)


# -- laser test-fire -------------------------------------------------------------


def grbl_sim(hostd: Running) -> GrblSimController:
    sim = hostd.daemon.sims[GRBL]
    assert isinstance(sim, GrblSimController)
    return sim


def grbl_board(hostd: Running) -> Any:
    return grbl_sim(hostd).board


async def test_a_laser_test_fires_then_always_ends_off(both: tuple[Running, Rpc]) -> None:
    hostd, rpc = both
    board = grbl_board(hostd)
    assert await rpc.call("machine.laser_test", machine=GRBL, power=5, duration_s=0.3) == {}
    powers = [power for _, power in board.beam]
    full = board.settings[30]
    assert 0.05 * full in powers  # it fired, at 5 % of $30
    assert max(powers) == 0.05 * full  # and never more
    assert powers[-1] == 0.0 and board.beam_power() == 0.0
    # A board fresh from its reset has no feed, and grbl refuses a G1 without one even
    # standing still (error:22): the G1 defines a slow one.
    fired = [ln for ln in lines_sent(hostd, GRBL) if ln.startswith((b"G1", b"G4", b"M5"))]
    assert fired[-3:] == [b"G1 F100 M3 S50", b"G4 P0.3", b"M5"]
    # A board with a feed of its own keeps it (asked with `$G` first).
    await rpc.call("machine.send", machine=GRBL, line="F750")
    assert await rpc.call("machine.laser_test", machine=GRBL, power=5, duration_s=0.3) == {}
    fired = [ln for ln in lines_sent(hostd, GRBL) if ln.startswith((b"G1", b"G4", b"M5"))]
    assert fired[-3:] == [b"G1 M3 S50", b"G4 P0.3", b"M5"]
    assert board.beam_power() == 0.0 and max(p for _, p in board.beam) == 0.05 * full


async def test_a_laser_test_ends_off_when_the_link_drops_mid_test(
    both: tuple[Running, Rpc],
) -> None:
    hostd, rpc = both
    board = grbl_board(hostd)
    firing = asyncio.create_task(
        rpc.call("machine.laser_test", machine=GRBL, power=5, duration_s=1.0)
    )
    await grbl_sim(hostd).wait_for(lambda: board.beam_power() > 0)
    await rpc.call("machine.disconnect", machine=GRBL)  # the host lets go of the port
    with pytest.raises(RpcFailure):
        await firing
    # The board had its M5 with the rest: the beam goes off when its own dwell ends.
    await grbl_sim(hostd).wait_for(lambda: board.beam_power() == 0.0)
    assert board.beam[-1][1] == 0.0


async def test_a_feedhold_during_a_laser_test_ends_the_beam(both: tuple[Running, Rpc]) -> None:
    hostd, rpc = both
    board = grbl_board(hostd)
    firing = asyncio.create_task(
        rpc.call("machine.laser_test", machine=GRBL, power=5, duration_s=1.0)
    )
    await grbl_sim(hostd).wait_for(lambda: board.beam_power() > 0)
    await rpc.call("machine.feedhold", machine=GRBL)
    await grbl_sim(hostd).wait_for(lambda: board.beam_power() == 0.0)
    await rpc.call("machine.cycle_start", machine=GRBL)
    await firing
    assert board.beam_power() == 0.0


async def test_laser_tests_refused_say_why_and_fire_nothing(both: tuple[Running, Rpc]) -> None:
    hostd, rpc = both
    board = grbl_board(hostd)
    err = await fails(-32602, rpc.call("machine.laser_test", machine=GRBL, power=50, duration_s=1))
    assert "laser_test_max" in err.message
    await fails(-32602, rpc.call("machine.laser_test", machine=GRBL, power=5, duration_s=3))
    await fails(-32602, rpc.call("machine.laser_test", machine=GRBL, power=0, duration_s=1))
    err = await fails(-32602, rpc.call("machine.laser_test", machine=G2, power=5, duration_s=1))
    assert "not a laser" in err.message
    assert [p for _, p in board.beam] == [0.0]
    job = await rpc.call("machine.jog", machine=GRBL, axes={"x": 50}, feed=100)
    await fails(1003, rpc.call("machine.laser_test", machine=GRBL, power=5, duration_s=1))
    await rpc.call("machine.jog_stop", machine=GRBL)
    await job_end(rpc, job["job"])


# -- frame -------------------------------------------------------------------

BOXED = "G21 G90\nG0 X12 Y7\nG1 X30 Y7 F800 S600 M4\nG1 X30 Y25\nG2 X20 Y15 I-5 J-5\nM5\n"


@pytest.mark.parametrize("machine", MACHINES)
async def test_frame_traces_the_bounding_box_with_the_beam_off(
    both: tuple[Running, Rpc], machine: str
) -> None:
    hostd, rpc = both
    (hostd.jobs / "boxed.gcode").write_text(BOXED)
    if machine == G2:  # a mill: up to the Z travel's top first, a place once homed
        await rpc.call("machine.home", machine=G2)
    before = len(traced(hostd, machine))
    job = await rpc.call("machine.frame", machine=machine, file="boxed.gcode")
    ended = await job_end(rpc, job["job"])
    assert ended["state"] == "completed", ended
    moves = traced(hostd, machine)[before:]
    corners = [(round(m.move.target["x"], 3), round(m.move.target["y"], 3)) for m in moves]
    # The arc from (30, 25) around (25, 20) bulges to X 25 + 50**0.5 (clockwise, it
    # never passes 90 degrees, so Y stays 25): the box has it.
    box = [(12, 7), (32.071, 7), (32.071, 25), (12, 25), (12, 7)]
    assert corners[-5:] == box
    assert not any(m.cutting for m in moves)  # the beam (or spindle) never on
    z = {round(m.move.target["z"], 3) for m in moves[-5:]}
    assert len(z) == 1  # at one height, never plunging


@pytest.mark.parametrize("laser", [False, True])
async def test_g2core_frames_right_after_power_on(tmp_path: Path, laser: bool) -> None:
    """Unhomed, no job run yet: a laser frames at its Z; a mill does not go to the Z
    travel's top (a place only once homed) but says how to frame; power above 0 on a
    build without a laser toolhead (no `th2mxs`) is refused saying so. Nothing moves
    for a refusal."""
    async with running_daemon(tmp_path, laser=laser) as hostd:
        rpc = await hostd.client()
        await rpc.call("subscribe", topics=["job"])
        await hostd.idle(rpc, G2)
        (hostd.jobs / "boxed.gcode").write_text(BOXED)
        snap = await rpc.call("machine.status", machine=G2)
        assert snap["homed"] is False and snap["job"] is None
        before = len(traced(hostd, G2))
        if not laser:
            err = await fails(-32602, rpc.call("machine.frame", machine=G2, file="boxed.gcode"))
            assert "safe_z" in err.message and "home" in err.message
            assert len(traced(hostd, G2)) == before
            return
        err = await fails(
            -32602, rpc.call("machine.frame", machine=G2, file="boxed.gcode", power=2)
        )
        assert "th2mxs" in err.message and "power 0" in err.message
        assert len(traced(hostd, G2)) == before
        job = await rpc.call("machine.frame", machine=G2, file="boxed.gcode")
        assert (await job_end(rpc, job["job"]))["state"] == "completed"
        moves = traced(hostd, G2)[before:]
        corners = [(round(m.move.target["x"], 3), round(m.move.target["y"], 3)) for m in moves]
        assert corners[-5:] == [(12, 7), (32.071, 7), (32.071, 25), (12, 25), (12, 7)]
        assert {round(m.move.target["z"], 3) for m in moves} == {0.0}  # at its Z
        assert not any(m.cutting for m in moves)
        await rpc.close()


async def test_frame_is_refused_only_when_its_xy_box_leaves_the_travel(
    both: tuple[Running, Rpc],
) -> None:
    """A frame traces the XY box and never lowers Z: a program that leaves the travel
    only in Z is refused by job.start but framed; one whose box leaves it in X is
    refused by both, and file.analyze said so beforehand (the page's Frame button)."""
    hostd, rpc = both
    await rpc.call("machine.home", machine=G2)  # the travel check runs on a homed machine
    await hostd.idle(rpc, G2)
    (hostd.jobs / "deep.gcode").write_text("G21 G90\nG0 X12 Y7\nG1 Z-5 F100\nG1 X30 Y25 F800\n")
    (hostd.jobs / "wide.gcode").write_text("G21 G90\nG0 X12 Y7\nG1 X350 Y25 F800\n")
    deep = await rpc.call("file.analyze", machine=G2, file="deep.gcode")
    wide = await rpc.call("file.analyze", machine=G2, file="wide.gcode")
    assert deep["travel_checked"] and wide["travel_checked"]
    assert [t[0] for t in deep["beyond_travel"]] == ["Z"] and deep["frame_beyond_travel"] == []
    assert [t[0] for t in wide["frame_beyond_travel"]] == ["X"]
    assert wide["frame_beyond_travel"] == wide["beyond_travel"]

    before = len(traced(hostd, G2))
    err = await fails(1008, rpc.call("machine.frame", machine=G2, file="wide.gcode"))
    assert err.data["beyond_travel"] == wide["frame_beyond_travel"]
    await fails(1008, rpc.call("job.start", machine=G2, file="deep.gcode"))
    assert len(traced(hostd, G2)) == before  # neither refusal moved anything

    job = await rpc.call("machine.frame", machine=G2, file="deep.gcode")
    assert (await job_end(rpc, job["job"]))["state"] == "completed"
    moves = traced(hostd, G2)[before:]
    corners = [(round(m.move.target["x"], 3), round(m.move.target["y"], 3)) for m in moves]
    assert corners[-5:] == [(12, 7), (30, 7), (30, 25), (12, 25), (12, 7)]
    assert min(m.move.target["z"] for m in moves) >= 0  # never down to the file's Z-5


async def test_a_mills_frame_crosses_no_lower_than_the_program_goes(tmp_path: Path) -> None:
    """The program rises to Z20 before it cuts; the machine's safe_z (5) is set lower. The
    frame climbs to Z20, where the program itself crosses, not to 5."""
    async with running_daemon(tmp_path, safe_z=5.0) as hostd:
        rpc = await hostd.client()
        await rpc.call("subscribe", topics=["job"])
        await hostd.idle(rpc, G2)
        text = "G21 G90\nG0 Z20\nG0 X12 Y7\nG1 Z-1 F100\nG1 X30 Y25 F800\nG0 Z20\n"
        (hostd.jobs / "clear.gcode").write_text(text)
        before = len(traced(hostd, G2))
        job = await rpc.call("machine.frame", machine=G2, file="clear.gcode")
        assert (await job_end(rpc, job["job"]))["state"] == "completed"
        assert any(line.endswith(b"G53 G0 Z20") for line in lines_sent(hostd, G2))
        moves = traced(hostd, G2)[before:]
        corners = [(round(m.move.target["x"], 3), round(m.move.target["y"], 3)) for m in moves]
        # The box of every move, the first rise at X0 Y0 too.
        assert corners[-5:] == [(0, 0), (30, 0), (30, 25), (0, 25), (0, 0)]
        assert {round(m.move.target["z"], 3) for m in moves[-5:]} == {20.0}
        await rpc.close()


async def test_frame_at_low_power_burns_only_along_the_box(both: tuple[Running, Rpc]) -> None:
    hostd, rpc = both
    (hostd.jobs / "boxed.gcode").write_text(BOXED)
    board = grbl_board(hostd)
    before = len(traced(hostd, GRBL))
    job = await rpc.call("machine.frame", machine=GRBL, file="boxed.gcode", power=2, feed=2000)
    await job_end(rpc, job["job"])
    moves = traced(hostd, GRBL)[before:]
    cutting = [m for m in moves if m.cutting]
    assert len(cutting) == 4 and all(m.move.speed == 0.02 * board.settings[30] for m in cutting)
    assert all(m.move.spindle == "M4" for m in cutting)  # dynamic power: none at rest
    assert board.beam_power() == 0.0


async def test_frame_refusals(both: tuple[Running, Rpc]) -> None:
    hostd, rpc = both
    (hostd.jobs / "boxed.gcode").write_text(BOXED)
    (hostd.jobs / "flat.gcode").write_text("G21\nM5\n")
    err = await fails(-32602, rpc.call("machine.frame", machine=G2, file="boxed.gcode", power=5))
    assert "not a laser" in err.message
    err = await fails(-32602, rpc.call("machine.frame", machine=GRBL, file="flat.gcode"))
    assert "no X and Y" in err.message
    await fails(1004, rpc.call("machine.frame", machine=GRBL, file="missing.gcode"))
    await fails(-32602, rpc.call("machine.frame", machine=GRBL, file="../boxed.gcode"))


# -- macros --------------------------------------------------------------------


async def test_macro_list_names_each_macro_with_its_params(both: tuple[Running, Rpc]) -> None:
    _, rpc = both
    listed = await rpc.call("macro.list", machine=GRBL)
    assert [m["name"] for m in listed] == ["corner", "wipe"]
    assert listed[0]["params"]["y"] == {"min": 0, "max": 40, "default": 3, "integer": False}
    assert "G0 X{x} Y{y}" in listed[0]["text"]
    every = await rpc.call("macro.list")
    assert {m["machine"] for m in every} == {G2, GRBL}
    await fails(1001, rpc.call("macro.list", machine="nope"))


@pytest.mark.parametrize("machine", MACHINES)
async def test_a_macro_runs_with_its_params_as_a_job(
    both: tuple[Running, Rpc], machine: str
) -> None:
    hostd, rpc = both
    job = await rpc.call("macro.run", machine=machine, name="corner", params={"x": 12.5})
    ended = await job_end(rpc, job["job"])
    assert ended["state"] == "completed" and ended["kind"] == "make", ended
    last = traced(hostd, machine)[-1].move.target
    assert (round(last["x"], 3), round(last["y"], 3)) == (12.5, 3)
    sent = lines_sent(hostd, machine)
    assert any(line.endswith(b"G0 X12.5 Y3") for line in sent)
    assert not any(b"to a corner" in line for line in sent)  # comments are not sent


@pytest.mark.parametrize(
    ("params", "why"),
    [
        ({"x": "5\nM3 S1000"}, "number"),
        ({"x": "5"}, "number"),
        ({"x": True}, "number"),
        ({"x": 5, "y": "1 M3 S1000"}, "number"),
        ({"x": 1e300}, "0 to 40"),
        ({"x": -1}, "0 to 40"),
        ({"x": 5, "feed": 100}, "no param"),
        ({}, "needs param"),
    ],
)
async def test_macro_params_cannot_smuggle_anything_in(
    both: tuple[Running, Rpc], params: dict[str, Any], why: str
) -> None:
    hostd, rpc = both
    err = await fails(-32602, rpc.call("macro.run", machine=GRBL, name="corner", params=params))
    assert why in err.message
    sent = lines_sent(hostd, GRBL)
    assert not any(b"M3" in line or line.startswith(b"G0 X") for line in sent)


async def test_an_unknown_macro_and_a_maintenance_macro_are_refused(
    both: tuple[Running, Rpc],
) -> None:
    hostd, rpc = both
    err = await fails(1004, rpc.call("macro.run", machine=GRBL, name="nope"))
    assert "corner" in err.message  # names the ones it has
    err = await fails(1008, rpc.call("macro.run", machine=GRBL, name="wipe"))
    assert "machine.maintenance" in err.message
    assert not any(line.startswith(b"$RST") for line in lines_sent(hostd, GRBL))
    await fails(1001, rpc.call("macro.run", machine="nope", name="corner"))
