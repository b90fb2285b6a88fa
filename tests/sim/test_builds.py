"""The simulated board as each g2core build behaves (hostd/protocol/g2builds.py).

Kills, flushes, alarms and holds differ between 100.26, 101.03 and 101.06;
each test names the build(s) whose source it follows (docs/protocol.md has the
table with files and lines).
"""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator
from dataclasses import replace
from pathlib import Path

import pytest

from hostd.protocol.states import MachineState
from hostd.sim import SimConfig, SimController

from .conftest import INSTANT, TIMED, Host, Message, dual, has_stat

pytestmark = pytest.mark.asyncio

LONG_MOVE = b"G1 X10 F600\n"  # a second at F600
WAITING = [f"G1 Y{i}".encode() for i in range(1, 30)]  # more than the planner takes


@contextlib.asynccontextmanager
async def single(tmp_path: Path, config: SimConfig) -> AsyncIterator[tuple[SimController, Host]]:
    async with SimController(str(tmp_path / "ttyG2"), config=config) as sim:
        host = await Host.open(sim.data_path)
        try:
            yield sim, host
        finally:
            await host.close()


def kills(messages: list[Message]) -> int:
    return sum(1 for m in messages if m.get("er", {}).get("st") == 207)


# -- ^D on two ports (101.x: xio_flush_to_command flushes the ^D's port alone) --------


@pytest.mark.parametrize("fb", [101.03, 101.06])
async def test_a_kill_on_the_control_port_leaves_the_data_ports_lines_to_run(
    tmp_path: Path, fb: float
) -> None:
    async with dual(tmp_path, replace(TIMED, fb=fb)) as (sim, control, data):
        await control.ask(b"{sr:{stat:t,posy:t}}\n")
        data.write(LONG_MOVE + b"".join(w + b"\n" for w in WAITING))
        await sim.wait_for(lambda: sim.planner_len == sim.config.planner_depth)
        control.send(b"\x04")
        await control.until(lambda m: m.get("er", {}).get("st") == 207)
        # The data port was not flushed: its waiting lines are read, answered and run.
        got = await control.until(lambda m: m.get("f", [0, 0, 0])[2] == len(WAITING[-1]) + 1)
        assert all(m["f"][1] == 0 for m in got if "f" in m)
        await sim.wait_for(lambda: sim.position["y"] > 0)


@pytest.mark.parametrize("fb", [101.03, 101.06])
async def test_a_kill_on_both_ports_flushes_both_and_is_told_twice(
    tmp_path: Path, fb: float
) -> None:
    async with dual(tmp_path, replace(TIMED, fb=fb)) as (sim, control, data):
        await control.ask(b"{sr:{stat:t,posy:t}}\n")
        data.write(LONG_MOVE + b"".join(w + b"\n" for w in WAITING))
        await sim.wait_for(lambda: sim.planner_len == sim.config.planner_depth)
        control.send(b"\x04")
        data.write(b"\x04\n")
        await control.until(lambda m: kills([m]) == 1)
        after = await control.until(lambda m: kills([m]) == 1)
        # The only answer after the kills is the marker's: nothing that waited was read.
        data.write(b"$xvm\n")
        after += await control.until(lambda m: "r" in m and "xvm" in m["r"])
        assert [m["f"] for m in after if "f" in m] == [[1, 0, 5]]
        assert sim.position["y"] == 0


@pytest.mark.parametrize("fb", [101.03, 101.06])
async def test_a_data_ports_kill_keeps_the_line_written_right_behind_it(
    tmp_path: Path, fb: float
) -> None:
    """The scan stops at each control (xio.cpp:795-804) and a ^D's flush drops only what
    was scanned before it (`flushToCommand`, `_read_offset = _scan_offset`, :1004): a
    line that came in behind the ^D, even in the same packet, is read after it."""
    async with dual(tmp_path, replace(TIMED, fb=fb)) as (sim, control, data):
        await control.ask(b"{sr:{stat:t,posy:t}}\n")
        data.write(LONG_MOVE + b"".join(w + b"\n" for w in WAITING))
        await sim.wait_for(lambda: sim.planner_len == sim.config.planner_depth)
        control.send(b"\x04")
        data.write(b"\x04\n$stat\n")  # one write: the ^D and the line behind it
        await control.until(lambda m: kills([m]) == 1)  # the control port's kill
        after = await control.until(lambda m: "r" in m and "stat" in m["r"])
        assert [m["f"] for m in after if "f" in m] == [[1, 0, 6]]  # nothing else was read
        assert after[-1]["r"]["stat"] == int(MachineState.PROGRAM_END)
        assert kills(after) == 1 and sim.position["y"] == 0  # the data port's kill, first


async def test_a_kill_on_one_port_flushes_the_lines_before_it(tmp_path: Path) -> None:
    async with single(tmp_path, replace(TIMED, fb=101.06)) as (sim, host):
        host.send(LONG_MOVE + b"".join(w + b"\n" for w in WAITING))
        await sim.wait_for(lambda: sim.planner_len == sim.config.planner_depth)
        host.send(b"\x04")
        await host.until(lambda m: kills([m]) == 1)
        answer = await host.ask(b"$xvm\n")
        assert answer["f"] == [1, 0, 5]  # the next answer is the marker's: the rest was dropped
        assert sim.position["y"] == 0
        assert sim.state == MachineState.PROGRAM_END


# -- 100.x: ^D is an ALARM, with no flush -------------------------------------------


async def test_before_101_02_a_kill_is_an_alarm_and_each_waiting_line_gets_204(
    tmp_path: Path,
) -> None:
    async with single(tmp_path, replace(TIMED, fb=100.26)) as (sim, host):
        host.send(LONG_MOVE + b"".join(w + b"\n" for w in WAITING))
        await sim.wait_for(lambda: sim.planner_len == sim.config.planner_depth)
        host.send(b"\x04")
        got = await host.until(lambda m: "er" in m)
        assert got[-1] == {"er": {"fb": 100.26, "st": 207, "msg": "Kill job - EOT Received"}}
        answered = sum(1 for m in got if "f" in m)
        # Every line not yet read when the ^D came is read and refused, none dropped.
        host.send(b"$xvm\n")
        rest = await host.until(lambda m: "xvm" in m.get("r", {}))
        assert [m["f"][1] for m in rest if "f" in m] == [204] * (len(WAITING) + 1 - answered) + [0]
        assert sim.state == MachineState.ALARM
        assert (await host.ask(b"{clear:n}\n"))["f"][1] == 0
        await host.until(has_stat(MachineState.PROGRAM_STOP))


async def test_before_101_02_there_is_no_gc2(tmp_path: Path) -> None:
    async with single(tmp_path, replace(INSTANT, fb=100.26)) as (_sim, host):
        assert (await host.ask(b'{"gc2":"G0 X1"}\n'))["f"][1] == 100


# -- alarms by build ------------------------------------------------------------------


async def test_101_03_never_enters_alarm_and_runs_lines_after_it(tmp_path: Path) -> None:
    async with single(tmp_path, replace(INSTANT, fb=101.03)) as (sim, host):
        sim.set_homed(True)
        sim.limit_switch("x")
        got = await host.until(lambda m: "er" in m)
        assert got[-1]["er"]["st"] == 203
        assert (await host.ask(b"G0 X1\n"))["f"][1] == 0  # not refused: no ALARM
        await sim.wait_for(lambda: sim.position["x"] == 1)
        assert sim.state != MachineState.ALARM


async def test_101_03_an_alarm_while_moving_ends_in_a_hold(tmp_path: Path) -> None:
    async with single(tmp_path, replace(TIMED, fb=101.03)) as (sim, host):
        await host.ask(b"{sr:{stat:t,hold:t}}\n")
        await host.ask(LONG_MOVE)
        await sim.wait_for(lambda: sim.position["x"] > 0)
        sim.limit_switch("x")
        got = await host.until(lambda m: m.get("sr", {}).get("hold") == 10)
        assert [m["er"]["st"] for m in got if "er" in m] == [203]
        assert sim.state == MachineState.HOLD


async def test_101_06_an_alarm_holds_first_then_kills_then_is_alarm(tmp_path: Path) -> None:
    async with single(tmp_path, replace(TIMED, fb=101.06)) as (sim, host):
        await host.ask(b"{sr:{stat:t,hold:t}}\n")
        await host.ask(LONG_MOVE)
        await sim.wait_for(lambda: sim.position["x"] > 0)
        sim.limit_switch("x")
        got = await host.until(has_stat(MachineState.ALARM))
        kinds = [
            "er203"
            if m.get("er", {}).get("st") == 203
            else "er207"
            if m.get("er", {}).get("st") == 207
            else f"stat{m['sr']['stat']}"
            if "stat" in m.get("sr", {})
            else "other"
            for m in got
        ]
        kinds = kinds[kinds.index("er203") :]
        assert "stat6" in kinds  # the reports say HOLD while the alarm's hold runs
        assert kinds.index("stat6") < kinds.index("er207") < kinds.index("stat2")


async def test_101_06_an_alarm_in_a_hold_is_reported_and_nothing_more(tmp_path: Path) -> None:
    async with single(tmp_path, replace(TIMED, fb=101.06)) as (sim, host):
        await host.ask(b"{sr:{stat:t,hold:t}}\n")
        await host.ask(LONG_MOVE)
        await sim.wait_for(lambda: sim.position["x"] > 0)
        host.send(b"!")
        await host.until(lambda m: m.get("sr", {}).get("hold") == 10)
        await host.ask(b"{alarm:n}\n")
        # cm_request_feedhold ignores a request unless the hold is off: no ALARM follows.
        assert (await host.ask(b"{stat:n}\n"))["r"] == {"stat": 6}


# -- `!` at rest ----------------------------------------------------------------------


async def test_101_06_a_feedhold_at_rest_is_a_silent_hold(tmp_path: Path) -> None:
    async with single(tmp_path, replace(INSTANT, fb=101.06)) as (sim, host):
        await host.ask(b"{sr:{stat:t,hold:t}}\n")
        host.send(b"!")
        got = await host.until(lambda m: m.get("sr", {}).get("hold") == 10)
        assert "stat" not in got[-1]["sr"]  # the state did not change
        host.send(b"G0 X1\n")
        assert (await host.ask(b"{stat:n}\n"))["r"] == {"stat": 1}
        await sim.wait_received(b"G0 X1")
        assert sim.position["x"] == 0  # read nothing: the line waits for the hold's end
        host.send(b"~")
        assert (await host.response())["f"] == [1, 0, 6]
        await sim.wait_for(lambda: sim.position["x"] == 1)


# -- overrides: settings named and enabled per build (docs/protocol.md, "Overrides") ---


async def test_before_101_02_the_overrides_are_mfo_and_off_until_enabled(tmp_path: Path) -> None:
    async with single(tmp_path, replace(TIMED, fb=100.26)) as (sim, host):
        answer = await host.ask(b'{"mfo":1.5}\n')
        assert answer["r"] == {"mfo": 1.5} and answer["f"][1] == 0
        assert sim._board.settings.override("feed") == 1.0  # mfoe is off (spindle.h:61 too)
        answer = await host.ask(b'{"mfoe":1}\n')
        assert sim._board.settings.override("feed") == 1.5
        answer = await host.ask(b'{"fro":1.2}\n')
        assert answer["f"][1] != 0  # no `fro` on 100.26


@pytest.mark.parametrize("fb", [101.03, 101.06])
async def test_from_101_02_fro_acts_froe_is_read_only_and_bounds_hold(
    tmp_path: Path, fb: float
) -> None:
    async with single(tmp_path, replace(TIMED, fb=fb)) as (sim, host):
        answer = await host.ask(b'{"fro":1.5}\n')
        assert answer["r"] == {"fro": 1.5}
        assert sim._board.settings.override("feed") == 1.5
        answer = await host.ask(b'{"froe":0}\n')
        assert answer["r"] == {"froe": 1}  # the setter is the getter
        assert sim._board.settings.override("feed") == 1.5
        too_fast = await host.ask(b'{"tro":1.5}\n')
        assert too_fast["f"][1] != 0 and sim._board.settings.override("rapid") == 1.0


async def test_a_program_end_puts_feed_and_traverse_back(tmp_path: Path) -> None:
    async with single(tmp_path, replace(INSTANT, fb=101.06)) as (sim, host):
        await host.ask(b'{"fro":1.5,"tro":0.5,"spo":0.7}\n')
        await host.ask(b"M30\n")
        await sim.wait_for(lambda: sim.state == MachineState.PROGRAM_END)
        settings = sim._board.settings
        assert (settings.override("feed"), settings.override("rapid")) == (1.0, 1.0)
        assert settings.override("spindle") == 0.7  # cm_reset_overrides leaves spo alone


# -- the spindle's keys: master's 100.26 `spe`/`spd`/`sps`, edge's 101.03 on `spc`/`sps` --


async def test_100_26_reports_its_spindle_as_enable_and_direction(tmp_path: Path) -> None:
    async with single(tmp_path, replace(INSTANT, fb=100.26)) as (_sim, host):
        assert (await host.ask(b"{spc:n}\n"))["f"][1] == 100  # no such key on master
        assert (await host.ask(b"{sr:{stat:t,spc:t}}\n"))["f"][1] == 100  # nor in the list
        assert (await host.ask(b"{sr:{stat:t,spe:t,spd:t,sps:t}}\n"))["f"][1] == 0
        await host.ask(b"M4 S9000\n")
        got = await host.until(lambda m: m.get("sr", {}).get("spe") == 1)
        assert got[-1]["sr"]["spd"] == 1 and got[-1]["sr"]["sps"] == 9000
        await host.ask(b"M5\n")
        await host.until(lambda m: m.get("sr", {}).get("spe") == 0)


@pytest.mark.parametrize("fb", [101.03, 101.06])
async def test_edge_reports_its_spindle_as_one_state(tmp_path: Path, fb: float) -> None:
    async with single(tmp_path, replace(INSTANT, fb=fb)) as (_sim, host):
        assert (await host.ask(b"{spe:n}\n"))["f"][1] == 100  # master's keys are gone
        assert (await host.ask(b"{spc:n}\n"))["r"] == {"spc": 0}
        assert (await host.ask(b"{sr:{stat:t,spc:t,sps:t}}\n"))["f"][1] == 0
        await host.ask(b"M3 S12000\n")
        got = await host.until(lambda m: m.get("sr", {}).get("spc") == 1)
        assert got[-1]["sr"]["sps"] == 12000
        await host.ask(b"M4\n")
        await host.until(lambda m: m.get("sr", {}).get("spc") == 2)
        await host.ask(b"M5\n")
        await host.until(lambda m: m.get("sr", {}).get("spc") == 0)
