"""Feedhold, resume, queue flush, job kill, interlock, homing and soft limits (seed 002)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from hostd.protocol.states import MachineState
from hostd.sim import SimController

from .conftest import INSTANT, Host, has_stat, responses, states

pytestmark = pytest.mark.asyncio

# 10 mm at 600 mm/min: one second, far longer than any test waits on it.
LONG_MOVE = b"G1 X10 F600\n"


async def start_moving(sim: SimController, host: Host) -> None:
    await host.ask(b"{sr:{stat:t,hold:t,posx:t,vel:t}}\n")
    await host.ask(LONG_MOVE)
    await sim.wait_for(lambda: sim.position["x"] > 0)


async def test_feedhold_stops_the_tool_and_cycle_start_resumes(
    timed_sim: SimController, timed_host: Host
) -> None:
    await start_moving(timed_sim, timed_host)
    timed_host.send(b"!")
    got = await timed_host.until(lambda m: m.get("sr", {}).get("hold") == 10)
    assert MachineState.HOLD in states(got)
    stopped_at = timed_sim.position["x"]
    assert 0 < stopped_at < 10
    assert got[-1]["sr"]["vel"] == 0
    timed_host.send(b"~")
    await timed_host.until(has_stat(5))
    await timed_sim.wait_for(lambda: timed_sim.position["x"] > stopped_at)
    timed_host.send(b"\x04")  # done: end the job rather than wait for it


@pytest.mark.parametrize("fb", [100.26, 101.03])
async def test_feedhold_is_ignored_when_not_moving(tmp_path: Path, fb: float) -> None:
    """100.26 and 101.03 honour `!` only while moving (g2builds.py); 101.06 holds at rest
    (tests/sim/test_builds.py)."""
    async with SimController(str(tmp_path / "ttyG2"), config=replace(INSTANT, fb=fb)) as sim:
        host = await Host.open(sim.data_path)
        try:
            # No hold; the `%` is a control all the same, right after a `!` (xio.cpp:754),
            # and a flush request with no hold does nothing but flush its port's input.
            host.send(b"!\n%\n$xvm\n")
            assert (await host.response()) == {"r": {"xvm": 6000}, "f": [1, 0, 5]}
            assert sim.state == MachineState.READY
            assert [r.kind for r in sim.received] == ["realtime", "realtime", "line"]
        finally:
            await host.close()


async def test_queue_flush_in_a_hold_drops_planned_and_buffered_lines(
    timed_sim: SimController, timed_host: Host
) -> None:
    await start_moving(timed_sim, timed_host)
    queued = [f"G1 Y{i}".encode() for i in range(1, 30)]  # more than the planner takes
    timed_host.send(b"".join(q + b"\n" for q in queued))
    await timed_sim.wait_received(queued[-1])
    timed_host.send(b"!%")
    got = await timed_host.until(has_stat(3))
    assert states(got)[-2:] == [MachineState.HOLD, MachineState.PROGRAM_STOP]
    assert timed_sim.planner_len == 0
    answered = len(responses(got))
    assert answered < len(queued)  # the rest were dropped without a response
    reply = await timed_host.ask(b"$xvm\n")
    assert reply["f"] == [1, 0, 5]
    assert timed_sim.position["y"] == 0


async def test_job_kill_while_moving_ends_the_program_with_a_207_report(
    timed_sim: SimController, timed_host: Host
) -> None:
    await start_moving(timed_sim, timed_host)
    queued = [f"G1 Y{i}".encode() for i in range(1, 30)]  # more than the planner takes
    timed_host.send(b"".join(q + b"\n" for q in queued))
    await timed_sim.wait_received(queued[-1])
    timed_host.send(b"\x04")
    got = await timed_host.until(has_stat(4))
    reports = [m["er"] for m in got if "er" in m]
    assert reports == [{"fb": 101.06, "st": 207, "msg": "Kill job - Job killed by ^d"}]
    assert len(responses(got)) < len(queued)  # the lines still buffered got no response
    assert timed_sim.state == MachineState.PROGRAM_END
    assert timed_sim.planner_len == 0
    reply = await timed_host.ask(b"$xvm\n")  # nothing of the killed job is answered any more
    assert reply["f"] == [1, 0, 5]


async def test_job_kill_when_idle_reports_at_once(host: Host) -> None:
    host.send(b"\x04")
    got = await host.until(has_stat(4))
    assert got[0] == {"er": {"fb": 101.06, "st": 207, "msg": "Kill job - Job killed by ^d"}}


async def test_enquiry_is_acknowledged(host: Host) -> None:
    host.send(b"\x05")
    assert (await host.message()) == {"ack": True}


async def test_in_hold_commands_run_at_once_in_the_secondary_planner(
    timed_sim: SimController, timed_host: Host
) -> None:
    await start_moving(timed_sim, timed_host)
    timed_host.send(b"!")
    await timed_host.until(lambda m: m.get("sr", {}).get("hold") == 10)
    hold_point = timed_sim.position["x"]
    timed_host.send(b"G1 Y1\n")  # raw lines keep filling the planner
    reply = await timed_host.ask(b'{gc2:"G91 G0 Z5"}\n')
    assert reply["f"][1] == 0
    assert timed_sim.position["z"] == pytest.approx(5)
    timed_host.send(b"~")
    await timed_host.until(has_stat(5))
    assert timed_sim.position["z"] == pytest.approx(0)  # back to the hold point
    assert timed_sim.position["x"] >= hold_point
    timed_host.send(b"\x04")


async def test_interlock_halts_without_an_exception_report_and_resumes(
    timed_sim: SimController, timed_host: Host
) -> None:
    await start_moving(timed_sim, timed_host)
    timed_sim.interlock(True)
    got = await timed_host.until(has_stat(MachineState.INTERLOCK))
    assert not [m for m in got if "er" in m]
    halted_at = timed_sim.position["x"]
    timed_sim.interlock(False)
    await timed_host.until(has_stat(MachineState.RUN))
    await timed_sim.wait_for(lambda: timed_sim.position["x"] > halted_at)
    timed_host.send(b"\x04")


async def test_homing_sets_homed_and_soft_limits_then_apply(host: Host, sim: SimController) -> None:
    assert (await host.ask(b"G0 X400\n"))["f"][1] == 0  # not homed: no soft limits
    assert (await host.ask(b"G28.2 X0 Y0 Z0\n"))["f"][1] == 0
    await sim.wait_for(lambda: sim.homed)
    assert sim.position == {"x": 0, "y": 0, "z": 0}
    host.send(b"G0 X350\n")
    got = await host.until(has_stat(2))
    errors = [m for m in got if "er" in m or "r" in m]
    assert errors == [
        {"er": {"fb": 101.06, "st": 222, "msg": "Soft limit - X max - soft_limits"}},
        {"r": {}, "f": [1, 222, 8]},  # the line itself is answered with the same code
        # then the alarm's hold (at rest, in place at once) runs its exit: a job kill
        {"er": {"fb": 101.06, "st": 207, "msg": "Kill job - Job killed by ^d"}},
    ]
    assert sim.state == MachineState.ALARM
    assert sim.position["x"] == 0


async def test_soft_limits_can_be_switched_off(host: Host, sim: SimController) -> None:
    sim.set_homed(True)
    await host.ask(b"{sl:0}\n")
    assert (await host.ask(b"G0 Z-5\n"))["f"][1] == 0
    assert (await host.ask(b"{sl:1}\n"))["f"][1] == 0
    assert (await host.ask(b"G0 Z-6\n"))["f"][1] == 225


async def test_g10_sets_the_stored_offsets_which_a_reset_keeps_and_the_groups_read(
    sim: SimController, host: Host
) -> None:
    """G10 L2/L20 (cm_set_g10_data), the `g54`.. groups (config_app.cpp, F_CONVERT), and
    the record of every move with its spindle (what the resume tests check)."""
    assert (await host.ask(b"G10 L2 P1 X20 Y10 Z40\n"))["f"][1] == 0
    await host.ask(b"S9000 M3\n")
    await host.ask(b"G0 X5 Y5 Z0\n")  # G54: machine 25, 15, 40
    await sim.wait_for(lambda: sim.position == {"x": 25.0, "y": 15.0, "z": 40.0})
    await host.ask(b"G10 L20 P2 X0 Y0\n")  # G55's origin is where the tool stands
    assert (await host.ask(b"{g55:n}\n"))["r"]["g55"] == {"x": 25, "y": 15, "z": 0}
    assert (await host.ask(b"G20\n"))["f"][1] == 0
    assert (await host.ask(b"{g54:n}\n"))["r"]["g54"]["x"] == round(20 / 25.4, 3)
    moves = [t.move for t in sim._board.traversed]
    assert moves[-1].target == {"x": 25.0, "y": 15.0, "z": 40.0}
    assert (moves[-1].spindle, moves[-1].speed) == ("M3", 9000)
    await sim.reset()
    again = await Host.open(sim.data_path)
    try:
        assert (await again.ask(b"{g55:n}\n"))["r"]["g55"] == {"x": 25, "y": 15, "z": 0}
        assert (await again.ask(b"{g92:n}\n"))["r"]["g92"] == {"x": 0, "y": 0, "z": 0}
    finally:
        await again.close()
