"""A board left running when the daemon stops, dies or loses the link mid-job.

A board runs on with what it holds when its host goes: the lines in its
buffer and planner, then it stands with the spindle or the beam the job left
on. The daemon stops it as a cancel does, on its way out (`stop_for_shutdown`)
or, after a crash or an unplug, as soon as it reaches the board again
(`ran_unwatched`). docs/operations.md, "When the daemon stops".
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from hostd.machine.events import JobChanged
from hostd.machine.supervisor import State as Sup
from hostd.protocol.commands import Realtime
from hostd.protocol.errors import Rejected
from hostd.protocol.states import MachineState as S
from hostd.protocol.status import Status
from hostd.sim.config import SimConfig
from hostd.sim.grbl import GrblConfig
from tests.machine.conftest import Bench, bench_for
from tests.machine.test_grbl import grbl_bench, state

pytestmark = pytest.mark.asyncio

SLOW = SimConfig(speed_factor=2.0)  # a job's buffered moves outlast the host's absence
SPINDLE_JOB = "G21 G90 M3 S8000\n" + "".join(
    f"G1 X{(i % 2) * 50} Y{i * 0.1:.1f} F3000\n" for i in range(200)
)


def kills(bench: Bench) -> int:
    """^D (the job kill) bytes the simulated g2core read, on any port."""
    return sum(1 for r in bench.sim.received if r.kind == "realtime" and r.data == b"\x04")


async def spindle(bench: Bench, want: str) -> None:
    """Until the board's own reports say the spindle is `want`."""
    engine = bench.machine.engine
    async with asyncio.timeout(10):
        await engine.wait_for(lambda: (engine.model.spindle or {}).get("state") == want)


async def at_rest(bench: Bench) -> None:
    engine = bench.machine.engine
    async with asyncio.timeout(10):
        await engine.wait_for(lambda: engine.model.state in (S.PROGRAM_STOP, S.PROGRAM_END))


async def test_a_daemon_stop_mid_job_kills_it_on_the_board_and_stops_the_spindle(
    tmp_path: Path,
) -> None:
    async with bench_for(tmp_path, sim_config=SLOW) as bench:
        bench.write("part.nc", SPINDLE_JOB)
        job = await bench.machine.start_make("part.nc")
        await spindle(bench, "cw")
        await bench.sim.wait_state(S.RUN)
        await bench.machine.stop_for_shutdown()
        row = await bench.job_ended(job.id)
        assert row.state == "interrupted"
        assert row.error is not None and row.error.code == 1002
        assert "stopped the board" in row.error.message
        assert kills(bench) >= 1
        # Not the 200 lines' worth it held: at rest, with the spindle off, at once.
        assert bench.sim.state in (S.PROGRAM_STOP, S.PROGRAM_END)
        await spindle(bench, "off")
        assert row.lines_acked < 200


async def test_a_daemon_stop_mid_grbl_laser_job_holds_resets_and_the_beam_is_off(
    tmp_path: Path,
) -> None:
    slow = GrblConfig(flavour="grbl", speed_factor=2.0, feedhold_decel=0.02)
    async with grbl_bench(tmp_path, slow) as bench:
        bench.write("raster.nc", "G21 G90 M3 S800\n" + SPINDLE_JOB.split("\n", 1)[1])
        job = await bench.machine.start_make("raster.nc")
        await state(bench, S.RUN)
        assert bench.board.board.beam_power() > 0
        await bench.machine.stop_for_shutdown()
        row = await bench.job_ended(job.id)
        assert row.state == "interrupted" and row.error is not None and row.error.code == 1002
        tx = bench.recorder.tx()
        assert tx.index("!") < tx.index("\x18")  # grbl's cancel: the hold, the reset at rest
        assert bench.board.board.beam_power() == 0.0
        assert bench.machine.engine.model.state is not S.ALARM  # no ALARM:3: it had stopped


async def test_a_daemon_stop_with_no_job_writes_nothing(tmp_path: Path) -> None:
    async with bench_for(tmp_path) as bench:
        assert (await bench.machine.engine.send("M3 S1000")).ok  # the operator's
        await spindle(bench, "cw")
        await bench.machine.stop_for_shutdown()
        assert kills(bench) == 0
        await spindle(bench, "cw")  # theirs to stop


async def test_a_board_left_running_by_an_unplug_is_stopped_when_it_is_back(
    tmp_path: Path,
) -> None:
    async with bench_for(tmp_path, sim_config=SLOW, auto_connect=True) as bench:
        bench.write("part.nc", SPINDLE_JOB)
        job = await bench.machine.start_make("part.nc")
        await spindle(bench, "cw")
        await bench.recorder.wait_for(  # the row knows a line the board ran
            lambda e: isinstance(e, JobChanged) and (e.job.get("line_executed") or 0) >= 2
        )
        await bench.sim.unplug()
        row = await bench.job_ended(job.id)
        assert row.state == "interrupted" and row.line_executed is not None
        await bench.supervisor(Sup.DISCONNECTED)
        assert bench.sim.state is S.RUN  # it runs on with what it holds, unwatched
        assert kills(bench) == 0
        # It runs at least two lines more while nobody watches.
        await bench.sim.wait_for(lambda: bench.sim.line > row.line_executed + 1)
        await bench.sim.replug()
        # Killed as soon as the link is back: idle at once, not 200 lines later.
        await bench.supervisor(Sup.IDLE)
        await at_rest(bench)
        await spindle(bench, "off")
        assert kills(bench) >= 1
        # The row's resume line is where the board was found running, not where the link
        # went: a resume does not run again the lines it ran meanwhile.
        told = await bench.recorder.wait_for(
            lambda e: (
                isinstance(e, JobChanged)
                and e.job["id"] == job.id
                and (e.job["line_executed"] or 0) > (row.line_executed or 0)
            )
        )
        assert isinstance(told, JobChanged) and told.job["state"] == "interrupted"
        assert told.job["line_executed"] >= row.line_executed + 2
        stored = await bench.store.get(job.id)
        assert stored is not None and stored.line_executed == told.job["line_executed"]


async def test_a_spindle_the_operator_left_on_is_left_on_across_an_unplug(
    tmp_path: Path,
) -> None:
    async with bench_for(tmp_path, auto_connect=True) as bench:
        assert (await bench.machine.engine.send("M3 S1000")).ok  # no operation of ours
        await spindle(bench, "cw")
        await bench.sim.unplug()
        await bench.supervisor(Sup.DISCONNECTED)
        await bench.sim.replug()
        await bench.supervisor(Sup.IDLE)
        await spindle(bench, "cw")
        assert kills(bench) == 0


async def test_after_a_crash_a_board_still_running_is_stopped_and_one_at_rest_is_not(
    tmp_path: Path,
) -> None:
    """`Daemon.run` hands each machine the rows it recovered; a machine told so stops a
    board found moving or with its spindle on, and leaves one at rest alone."""
    async with bench_for(tmp_path, sim_config=SLOW, auto_connect=True) as bench:
        bench.write("part.nc", SPINDLE_JOB)
        await bench.machine.start_make("part.nc")
        await bench.sim.wait_state(S.RUN)
        # The daemon dies: its port closes, and the board runs on.
        await bench.machine.disconnect()
        assert bench.sim.state is S.RUN
        bench.machine.ran_unwatched("job 1 was under way when the daemon stopped")
        await bench.machine.connect()
        await at_rest(bench)
        await spindle(bench, "off")
        assert kills(bench) >= 1
        # Once: a later reconnect, with nothing under way, does nothing.
        before = kills(bench)
        await bench.machine.disconnect()
        bench.machine.ran_unwatched("job 1 was under way when the daemon stopped")
        await bench.machine.connect()
        await bench.supervisor(Sup.IDLE)
        assert kills(bench) == before  # at rest, spindle off: nothing to stop


async def test_a_kill_the_session_refuses_at_the_connect_leaves_the_link_up(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The kill runs from the engine's delivery loop, after the events of the connect: a
    refusal there is logged, and the machine stays connected and answers."""
    async with bench_for(tmp_path, sim_config=SLOW, auto_connect=True) as bench:
        bench.write("part.nc", SPINDLE_JOB)
        await bench.machine.start_make("part.nc")
        await bench.sim.wait_state(S.RUN)
        await bench.machine.disconnect()
        session = bench.machine.engine.session

        def refused(command: Realtime) -> None:
            raise Rejected(Status.COMMAND_REJECTED_BY_ALARM, "refused for the test")

        monkeypatch.setattr(session, "realtime", refused)
        await bench.machine.connect()
        assert (await bench.machine.engine.send("{fbc:n}")).ok  # still connected
        assert kills(bench) == 0
        assert bench.machine.supervisor.state is not Sup.DISCONNECTED


async def test_a_resume_line_that_cannot_be_written_leaves_the_machine_serving(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The row's new line is written by a task of the machine's own: a store that fails
    then (a full disk) is logged, and the machine, its board stopped, goes on."""
    async with bench_for(tmp_path, sim_config=SLOW, auto_connect=True) as bench:
        bench.write("part.nc", SPINDLE_JOB)
        job = await bench.machine.start_make("part.nc")
        await bench.recorder.wait_for(
            lambda e: isinstance(e, JobChanged) and (e.job.get("line_executed") or 0) >= 2
        )
        await bench.sim.unplug()
        row = await bench.job_ended(job.id)
        assert row.line_executed is not None  # the board runs on past it, unwatched:
        await bench.sim.wait_for(lambda: bench.sim.line > row.line_executed + 1)

        async def full(*args: object, **kwargs: object) -> None:
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(bench.store, "update", full)
        await bench.sim.replug()
        await bench.supervisor(Sup.IDLE)
        await spindle(bench, "off")
        assert (await bench.machine.engine.send("{fbc:n}")).ok  # still serving
