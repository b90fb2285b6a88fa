"""The engine over real ptys against the simulator, on each g2core build it accepts.

The sequences of issue 26 that real boards produce, each on every build it
applies to (the rules: hostd/protocol/g2builds.py; the table of sources:
docs/protocol.md, "Firmware builds").
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from dataclasses import replace
from pathlib import Path

import pytest

from hostd.machine.engine import Engine
from hostd.machine.events import FaultDetected
from hostd.machine.stream import JobStream
from hostd.protocol.commands import Realtime
from hostd.protocol.errors import Rejected
from hostd.protocol.program import program_lines
from hostd.protocol.states import MachineState as S
from hostd.protocol.vocabulary import StreamEnd
from hostd.sim import SimController
from tests.machine.conftest import FAST, Recorder, Rig, machine_config, running

pytestmark = pytest.mark.asyncio

# Moves long enough to be still running when the test acts, with a planner that
# fills: lines wait in the board's serial input, where a kill must reach them.
SLOW = replace(FAST, speed_factor=5.0, planner_depth=8)
JOB = [f"G1 X{5 + i % 2 * 5} Y{i % 7} F3000" for i in range(60)]


@contextlib.asynccontextmanager
async def rig_for(tmp_path: Path, fb: float, *, dual: bool) -> AsyncIterator[Rig]:
    data = str(tmp_path / "data")
    control = str(tmp_path / "ctrl") if dual else None
    async with SimController(data, control_path=control, config=replace(SLOW, fb=fb)) as sim:
        recorder = Recorder()
        # A window wider than the planner: lines wait in the board's input.
        engine = Engine(machine_config(data, control, window=12), recorder)
        engine.console = True
        async with running(engine):
            await engine.connect()
            yield Rig(sim, engine, recorder)


def faults(rig: Rig) -> list[str]:
    return [e.fault for e in rig.recorder.events if isinstance(e, FaultDetected)]


async def result(stream: JobStream) -> StreamEnd:
    async with asyncio.timeout(10):
        return (await stream.result).end


async def moving(rig: Rig, stream: JobStream) -> None:
    rig.engine.start_stream(stream)
    await rig.sim.wait_for(lambda: rig.sim.state is S.RUN and rig.sim.position["x"] > 0)
    await rig.sim.wait_for(lambda: rig.sim.planner_len == SLOW.planner_depth)


async def settled(rig: Rig) -> None:
    """Every line hostd wrote is answered: what the board was going to read, it read."""
    async with asyncio.timeout(10):
        await rig.engine.wait_for(lambda: not rig.engine.session.flushing())
    await rig.engine.send("$xvm")  # a data line: answered after any still waiting


# -- item 1: a cancel stops the board on both ports -----------------------------------


@pytest.mark.parametrize("fb", [101.03, 101.06])
@pytest.mark.parametrize("dual", [False, True], ids=["one-port", "two-ports"])
async def test_a_cancel_leaves_nothing_to_run_and_accounts_every_line(
    tmp_path: Path, fb: float, dual: bool
) -> None:
    async with rig_for(tmp_path, fb, dual=dual) as rig:
        stream = JobStream(program_lines(JOB))
        await moving(rig, stream)
        rig.engine.realtime(Realtime.JOB_KILL)
        assert await result(stream) is StreamEnd.CANCELLED
        await rig.sim.wait_state(S.PROGRAM_END)
        await settled(rig)
        stopped_at = dict(rig.sim.position)
        assert rig.sim.planner_len == 0 and rig.sim.state is S.PROGRAM_END
        assert stream.acked + stream.rejected + stream.discarded == stream.sent
        assert stream.discarded > 0
        assert faults(rig) == []  # no answer came for a line booked as discarded
        await rig.engine.send("{stat:n}")
        assert rig.sim.position == stopped_at  # nothing ran after the cancel


@pytest.mark.parametrize("fb", [101.03, 101.06])
async def test_kills_that_merge_leave_the_books_empty_and_the_next_job_runs_whole(
    tmp_path: Path, fb: float
) -> None:
    """Two cancels at once on two ports: four ^Ds, and the two on the control port merge
    into one kill and one `er` 207 (cm_request_job_kill sets a flag, cycle_feedhold.cpp:523;
    the hold's end runs one `_run_job_kill`, :551-553). The data port's lines the ^Ds
    threw away are known by the fence behind each ^D, not by counting reports."""
    async with rig_for(tmp_path, fb, dual=True) as rig:
        stream = JobStream(program_lines(JOB))
        await moving(rig, stream)
        assert rig.engine.session.unanswered() > 0  # lines wait in the board's input
        rig.engine.realtime(Realtime.JOB_KILL)
        rig.engine.realtime(Realtime.JOB_KILL)  # both reach the board while it decelerates
        assert await result(stream) is StreamEnd.CANCELLED
        async with asyncio.timeout(10):
            await rig.engine.wait_for(lambda: not rig.engine.session.flushing())
        kills = [r.port for r in rig.sim.received if r.data == b"\x04"]
        reports = [s for s in rig.sim.sent if b'"st":207' in s.data]
        assert sorted(kills) == ["control", "control", "data", "data"]
        assert len(reports) == 3  # the control port's two kills merged
        assert rig.engine.session.unanswered() == 0  # nothing left on the books
        assert stream.acked + stream.rejected + stream.discarded == stream.sent
        assert stream.discarded > 0 and faults(rig) == []
        # The window is free and the answers are the new job's own.
        again = JobStream(program_lines(JOB[:20]))
        rig.engine.start_stream(again)
        assert await result(again) is StreamEnd.COMPLETED
        assert again.acked == again.sent == 20
        assert faults(rig) == []


# -- item 5: before 101.02 a cancel is an ALARM, settled by its 204s, then cleared -------


@pytest.mark.parametrize("dual", [False, True], ids=["one-port", "two-ports"])
async def test_before_101_02_a_cancel_ends_cleared_with_no_fault(
    tmp_path: Path, dual: bool
) -> None:
    async with rig_for(tmp_path, 100.26, dual=dual) as rig:
        stream = JobStream(program_lines(JOB))
        await moving(rig, stream)
        rig.engine.realtime(Realtime.JOB_KILL)
        assert await result(stream) is StreamEnd.CANCELLED
        async with asyncio.timeout(10):
            await rig.engine.wait_for(lambda: rig.engine.model.state is S.PROGRAM_STOP)
        assert rig.sim.state is S.PROGRAM_STOP  # hostd cleared the ALARM its ^D made
        assert stream.acked + stream.rejected + stream.discarded == stream.sent
        assert faults(rig) == []
        assert b'{"clear":null}' in [
            r.data for r in rig.sim.received if r.port == "data" and r.kind == "line"
        ]


# -- items 2 and 3: an alarm through a hold keeps its lockout and its reason --------------


async def test_101_06_a_limit_mid_job_stays_locked_with_its_reason(tmp_path: Path) -> None:
    async with rig_for(tmp_path, 101.06, dual=False) as rig:
        stream = JobStream(program_lines(JOB))
        await moving(rig, stream)
        rig.sim.limit_switch("x")
        assert await result(stream) is StreamEnd.FAILED
        await rig.sim.wait_state(S.ALARM)
        async with asyncio.timeout(5):
            await rig.engine.wait_for(lambda: rig.engine.model.state is S.ALARM)
        assert any(s.data.count(b'"st":207') for s in rig.sim.sent)  # its own kill came
        assert "Limit" in (rig.engine.model.last_exception_message() or "")
        with pytest.raises(Rejected, match="Limit"):
            await rig.engine.send("G0 X1")
        assert faults(rig) == []


# -- item 4: 101.03 never enters ALARM: hostd stops it and keeps the lockout --------------


async def test_101_03_a_limit_is_stopped_by_hostd_and_held_until_a_clear(
    tmp_path: Path,
) -> None:
    async with rig_for(tmp_path, 101.03, dual=False) as rig:
        stream = JobStream(program_lines(JOB))
        await moving(rig, stream)
        rig.sim.limit_switch("x")
        assert await result(stream) is StreamEnd.FAILED
        await rig.sim.wait_for(lambda: rig.sim.state is S.PROGRAM_END)  # hostd's kill ran
        await settled(rig)
        assert rig.sim.planner_len == 0 and rig.sim.state is not S.ALARM
        assert rig.engine.model.state is S.ALARM  # hostd's own lockout
        with pytest.raises(Rejected, match="Limit"):
            await rig.engine.send("G0 X1")
        await rig.engine.clear()
        assert rig.engine.model.state is S.PROGRAM_END
        await rig.engine.send("G0 X1")


# -- item 6: a hold at rest shows in `hold` alone ----------------------------------------


async def test_101_06_a_feedhold_at_rest_holds_job_lines_until_resumed(tmp_path: Path) -> None:
    async with rig_for(tmp_path, 101.06, dual=False) as rig:
        rig.engine.realtime(Realtime.FEEDHOLD)
        async with asyncio.timeout(5):
            await rig.engine.wait_for(lambda: rig.engine.model.hold == 10)
        assert rig.engine.model.state is S.READY
        stream = JobStream(program_lines(JOB[:3]))
        rig.engine.start_stream(stream)
        await rig.engine.send("{stat:n}")
        assert not any(r.data.startswith(b"N1 ") for r in rig.sim.received)
        await rig.engine.send("G0 Z1")  # a client's line in the hold runs inside it
        assert b'{"gc2":"G0 Z1"}' in [r.data for r in rig.sim.received]
        rig.engine.realtime(Realtime.CYCLE_START)
        assert await result(stream) is StreamEnd.COMPLETED


# -- item 8: the clear goes on the data port -------------------------------------------


@pytest.mark.parametrize("fb", [100.26, 101.06])
async def test_a_clear_goes_on_the_data_port(tmp_path: Path, fb: float) -> None:
    async with rig_for(tmp_path, fb, dual=True) as rig:
        await rig.engine.send("{alarm:n}")
        async with asyncio.timeout(5):
            await rig.engine.wait_for(lambda: rig.engine.model.state is S.ALARM)
        await rig.engine.clear()
        clears = [r.port for r in rig.sim.received if r.data == b'{"clear":null}']
        assert clears == ["data"]
        assert rig.sim.state is S.PROGRAM_STOP


@pytest.mark.parametrize("fb", [100.26, 101.03, 101.06])
async def test_a_feedhold_and_flush_on_two_ports_leaves_nothing_to_run(
    tmp_path: Path, fb: float
) -> None:
    """Before 101.05 a `%` flushes its own port alone: hostd sends `!` `%` on the data port
    too; 101.05+ flushes every data port once held (docs/protocol.md, "Firmware builds")."""
    async with rig_for(tmp_path, fb, dual=True) as rig:
        stream = JobStream(program_lines(JOB))
        await moving(rig, stream)
        rig.engine.realtime(Realtime.FEEDHOLD)
        rig.engine.realtime(Realtime.QUEUE_FLUSH)
        assert await result(stream) is StreamEnd.CANCELLED
        await rig.sim.wait_state(S.PROGRAM_STOP)
        await settled(rig)
        stopped_at = dict(rig.sim.position)
        assert rig.sim.planner_len == 0
        assert stream.acked + stream.rejected + stream.discarded == stream.sent
        assert stream.discarded > 0
        assert faults(rig) == []
        await rig.engine.send("{stat:n}")
        assert rig.sim.position == stopped_at and rig.sim.state is S.PROGRAM_STOP
