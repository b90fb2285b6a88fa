"""ALARM, SHUTDOWN and PANIC: entering, draining and rejecting, clearing (seed 000)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from hostd.protocol.states import MachineState
from hostd.sim import SimController

from .conftest import TIMED, Host, has_stat

pytestmark = pytest.mark.asyncio


async def test_limit_switch_alarm_rejects_actions_but_answers_gets(
    host: Host, sim: SimController
) -> None:
    sim.set_homed(True)
    sim.limit_switch("y")
    got = await host.until(has_stat(MachineState.ALARM))
    assert got[0] == {
        "er": {
            "fb": 101.06,
            "st": 203,
            "msg": "Limit hit [$clear to reset, $lim=0 to override] - input 3",
        }
    }
    assert not sim.homed
    assert (await host.ask(b"G0 X1\n")) == {"r": {}, "f": [1, 204, 6]}
    assert (await host.ask(b"{xvm:100}\n"))["f"][1] == 204
    assert (await host.ask(b"$xvm=100\n"))["f"][1] == 204
    assert (await host.ask(b'{"gc":"G0 X1"}\n'))["f"][1] == 204
    assert (await host.ask(b"{xvm:n}\n")) == {"r": {"xvm": 6000}, "f": [1, 0, 9]}
    assert (await host.ask(b"{clear:n}\n"))["f"] == [1, 0, 11]
    await host.until(has_stat(MachineState.PROGRAM_STOP))
    assert (await host.ask(b"G0 X1\n"))["f"][1] == 0


@pytest.mark.parametrize(
    ("fb", "kills"),
    [
        (100.26, []),  # cm_alarm sets ALARM at once (canonical_machine.cpp:969)
        # `_run_alarm` kills the job once held: its own 207, then ALARM (cycle_feedhold.cpp:354)
        (101.06, [{"fb": 101.06, "st": 207, "msg": "Kill job - Job killed by ^d"}]),
    ],
)
async def test_lines_waiting_in_an_alarm_are_drained_and_rejected(
    tmp_path: Path, fb: float, kills: list[dict[str, object]]
) -> None:
    config = replace(TIMED, fb=fb)
    async with SimController(str(tmp_path / "ttyG2"), config=config) as timed_sim:
        timed_host = await Host.open(timed_sim.data_path)
        try:
            timed_host.send(b"G1 X10 F600\n" + b"G1 Y1\n" * 40)  # more than the planner takes
            await timed_sim.wait_for(
                lambda: timed_sim.planner_len == timed_sim.config.planner_depth
            )
            timed_host.send(b"{alarm:n}\n")
            got = await timed_host.until(lambda m: m.get("f", [0, 0])[1] == 204)
            er = [m["er"] for m in got if "er" in m]
            alarm = {"fb": fb, "st": 18, "msg": "System alarm - sent by host"}
            assert er == [alarm, *kills]
            assert timed_sim.planner_len == 0
            await timed_sim.wait_for(
                lambda: sum(1 for s in timed_sim.sent if b",204," in s.data) > 20
            )
        finally:
            await timed_host.close()


async def test_a_set_form_clear_is_rejected_in_alarm(host: Host, sim: SimController) -> None:
    await host.ask(b"{alarm:n}\n")
    assert (await host.ask(b"{clear:1}\n"))["f"][1] == 204
    assert (await host.ask(b"$clear=1\n"))["f"][1] == 204
    assert sim.state == MachineState.ALARM
    assert (await host.ask(b"$clear\n"))["f"] == [1, 0, 7]
    await sim.wait_state(MachineState.PROGRAM_STOP, timeout=1)


async def test_m30_clears_an_alarm_and_an_n_word_defeats_it(host: Host, sim: SimController) -> None:
    await host.ask(b"{alarm:n}\n")
    assert (await host.ask(b"N5 M30\n"))["f"][1] == 204
    assert (await host.ask(b"m30\n"))["f"][1] == 0
    got = await host.until(has_stat(MachineState.PROGRAM_END))
    assert MachineState.ALARM not in [m["sr"].get("stat") for m in got if "sr" in m]
    assert sim.state == MachineState.PROGRAM_END


async def test_estop_shuts_down_and_a_clear_ends_the_program(
    host: Host, sim: SimController
) -> None:
    sim.set_homed(True)
    sim.estop(True)
    got = await host.until(has_stat(MachineState.SHUTDOWN))
    assert got[0] == {"er": {"fb": 101.06, "st": 5, "msg": "System shutdown - input 7"}}
    assert not sim.homed
    assert (await host.ask(b"G0 X1\n"))["f"][1] == 205
    sim.estop(False)  # releasing the input clears nothing
    assert (await host.ask(b"{stat:n}\n"))["r"] == {"stat": 12}
    assert (await host.ask(b"{clr:n}\n")) == {"r": {"clr": None}, "f": [1, 0, 9]}
    await host.until(has_stat(MachineState.PROGRAM_END))


async def test_panic_rejects_everything_and_only_a_reset_leaves_it(
    host: Host, sim: SimController
) -> None:
    sim.panic()
    got = await host.until(has_stat(MachineState.PANIC))
    assert got[0]["er"]["st"] == 6
    assert (await host.ask(b"G0 X1\n"))["f"][1] == 206
    assert (await host.ask(b"{clear:n}\n"))["f"][1] == 0  # answered, but nothing changes
    assert (await host.ask(b"M30\n"))["f"][1] == 206
    assert sim.state == MachineState.PANIC
    host.send(b"\x18")
    await host.hangup()
    await host.close()
    await sim.wait_for(lambda: sim.state == MachineState.READY)
    fresh = await Host.open(sim.data_path)
    try:
        assert (await fresh.ask(b"{stat:n}\n"))["r"] == {"stat": 1}
    finally:
        await fresh.close()


async def test_shutdown_by_command_and_job_kill_is_ignored_in_it(
    host: Host, sim: SimController
) -> None:
    await host.ask(b"{shutd:n}\n")
    assert sim.state == MachineState.SHUTDOWN
    # 101.06 reaches SHUTDOWN through a hold and a job kill of its own: one 207 so far.
    assert len([s for s in sim.sent if b'"st":207' in s.data]) == 1
    host.send(b"\x04")
    assert (await host.ask(b"{stat:n}\n"))["r"] == {"stat": 12}
    assert len([s for s in sim.sent if b'"st":207' in s.data]) == 1
