"""The same machine layer over a grbl board: the simulated grbl 1.1h / grblHAL on a real pty.

Every test drives `Machine` (supervisor, jobs, faults) exactly as the API
does; only `dialect = "grbl"` differs from the g2core tests.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from hostd.machine import operations
from hostd.machine.events import Console, FaultChanged, LinkChanged, StatusChanged
from hostd.machine.jobstore import JobStore
from hostd.machine.machine import Machine
from hostd.machine.supervisor import State as Sup
from hostd.protocol.commands import Realtime
from hostd.protocol.errors import Busy, ControllerError, Rejected
from hostd.protocol.states import MachineState as S
from hostd.sim.grbl import GrblConfig, GrblSimController
from tests.machine.conftest import Bench, Recorder, machine_config

pytestmark = pytest.mark.asyncio

GRBL = GrblConfig(flavour="grbl", speed_factor=50.0, feedhold_decel=0.02)
HAL = GrblConfig(flavour="grblhal", speed_factor=50.0, feedhold_decel=0.02)


@dataclass
class GrblBench(Bench):
    grbl: GrblSimController | None = None

    @property
    def board(self) -> GrblSimController:
        assert self.grbl is not None
        return self.grbl


@contextlib.asynccontextmanager
async def grbl_bench(
    tmp_path: Path, config: GrblConfig = GRBL, *, idle: bool = True, **overrides: object
) -> AsyncIterator[GrblBench]:
    """`idle`: wait for the supervisor to be idle (a board with homing on starts in ALARM)."""
    path = str(tmp_path / "ttyACM0")
    jobs = tmp_path / "jobs"
    jobs.mkdir(exist_ok=True)
    store = JobStore(tmp_path / "jobs.db")
    async with GrblSimController(path, config) as sim:
        machine = Machine(
            machine_config(
                path,
                dialect="grbl",
                **{"handshake_timeout": 2.0, "status_interval": 0.1, **overrides},
            ),
            store,
            jobs,
        )
        machine.engine.console = True  # the recorder reads the traffic
        recorder = Recorder()
        machine.hub.subscribe(recorder)
        task = asyncio.create_task(machine.serve())
        try:
            await machine.connect()
            bench = GrblBench(None, machine, store, recorder, jobs, sim)  # type: ignore[arg-type]
            if idle:
                await bench.supervisor(Sup.IDLE)
            yield bench
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
            store.close()


async def state(bench: GrblBench, want: S) -> None:
    engine = bench.machine.engine
    async with asyncio.timeout(5):
        await engine.wait_for(lambda: engine.model.state is want)


async def test_a_grbl_board_connects_to_idle_and_says_what_it_is(tmp_path: Path) -> None:
    async with grbl_bench(tmp_path, GrblConfig(flavour="grbl", laser_mode=True)) as bench:
        snap = bench.machine.snapshot()
        assert snap["dialect"] == "grbl"
        assert snap["state"]["name"] == "READY" and snap["board_state"] == "Idle"
        assert snap["laser_mode"] is True
        assert snap["units"] == "mm" and snap["wcs"] == "G54"
        session = bench.machine.engine.session
        assert (session.flavour, session.rx_size) == ("Grbl", 128)  # type: ignore[attr-defined]


async def test_grblhal_without_a_banner_is_asked_and_its_buffer_read(tmp_path: Path) -> None:
    async with grbl_bench(tmp_path, HAL) as bench:
        session = bench.machine.engine.session
        assert session.rx_size == 1024 and session.blocks == 100  # type: ignore[attr-defined]
        assert bench.machine.snapshot()["board_state"] == "Idle"


@pytest.mark.parametrize("config", [GRBL, HAL], ids=["grbl", "grblhal"])
async def test_a_2000_line_job_never_overfills_the_receive_buffer(
    tmp_path: Path, config: GrblConfig
) -> None:
    async with grbl_bench(tmp_path, config) as bench:
        body = "".join(f"G1 X{i % 50}.5 Y{i % 7} F20000 (move {i}!)\n" for i in range(2000))
        bench.write("long.nc", "G21 G90\n" + body)
        job = await bench.machine.start_make("long.nc")
        done = await bench.job_ended(job.id)
        assert done.state == "completed", done.error
        assert done.lines_acked == done.lines_sent == 2001
        assert bench.board.board.rx_dropped == 0
        assert bench.machine.supervisor.state is Sup.IDLE


async def test_hold_and_resume_a_grbl_job(tmp_path: Path) -> None:
    slow = GrblConfig(flavour="grbl", speed_factor=5.0, feedhold_decel=0.02)
    async with grbl_bench(tmp_path, slow) as bench:
        bench.write("job.nc", "".join(f"G1 X{i % 20} F3000\n" for i in range(60)))
        job = await bench.machine.start_make("job.nc")
        await state(bench, S.RUN)
        bench.machine.pause()
        await state(bench, S.HOLD)
        await bench.board.wait_state("Hold:0")
        written = len(bench.board.received)
        with pytest.raises(Busy, match="grbl runs no line inside"):
            await bench.machine.engine.send("M5")
        await state(bench, S.HOLD)  # a report later, still nothing more written
        assert len([r for r in bench.board.received[written:] if r.kind == "line"]) == 0
        bench.machine.resume()
        done = await bench.job_ended(job.id)
        assert done.state == "completed" and done.lines_acked == 60


async def test_a_resumed_job_runs_on_without_waiting_for_a_status_poll(tmp_path: Path) -> None:
    """grbl reports a `?` read with the `~` before it resumes (protocol.c): the host asks
    until a report shows the hold left, and the job's lines flow at once. Before, they
    waited for the next poll (a minute here)."""
    slow = GrblConfig(flavour="grbl", speed_factor=5.0, feedhold_decel=0.02)
    async with grbl_bench(tmp_path, slow, status_interval=60.0) as bench:
        bench.write("job.nc", "".join(f"G1 X{i % 20} F3000\n" for i in range(400)))
        await bench.machine.start_make("job.nc")
        board = bench.board
        await board.wait_state("Run")  # (the host hears of it at its next poll)
        bench.machine.pause()
        await board.wait_state("Hold:0")
        await state(bench, S.HOLD)  # a poll soon after the `!`, not a minute away

        def job_lines() -> int:
            return b"".join(r.data for r in board.received).count(b"G1 ")

        before = job_lines()
        assert before < 400
        bench.machine.resume()
        await board.wait_for(lambda: job_lines() > before, timeout=20)  # the poll: 60 s
        assert bench.machine.current_job().state == "running"  # type: ignore[union-attr]


async def test_a_jobs_end_is_seen_without_waiting_for_a_status_poll(tmp_path: Path) -> None:
    """grbl tells nothing when its planner runs dry: once every line is answered, the host
    asks every END_POLL until a report shows the board at rest. Before, the end waited for
    the next poll (a minute here) while the board stood idle."""
    slow = GrblConfig(flavour="grbl", speed_factor=5.0, feedhold_decel=0.02)
    async with grbl_bench(tmp_path, slow, status_interval=60.0) as bench:
        bench.write("job.nc", "".join(f"G1 X{i % 20} F3000\n" for i in range(40)))
        job = await bench.machine.start_make("job.nc")
        board = bench.board

        def moved_all() -> bool:  # every line read, the last move run: true from then on
            lines = b"".join(r.data for r in board.received).count(b"G1 ")
            return lines == 40 and board.state == "Idle"

        await board.wait_for(moved_all, timeout=20)
        async with asyncio.timeout(5):  # a minute before, at the next poll
            done = await bench.job_ended(job.id)
        assert done.state == "completed" and done.lines_acked == 40


async def test_a_resume_given_while_the_hold_still_decelerates_runs_the_job_on(
    tmp_path: Path,
) -> None:
    """grbl drops a `~` read with its `!` or while the hold decelerates (protocol.c,
    EXEC_CYCLE_START): the host keeps it until a report shows Hold:0, so a quick
    resume is not lost, with the board held while the host says the job runs."""
    slow = GrblConfig(flavour="grbl", speed_factor=5.0, feedhold_decel=0.3)
    async with grbl_bench(tmp_path, slow) as bench:
        bench.write("job.nc", "".join(f"G1 X{i % 20} F3000\n" for i in range(40)))
        job = await bench.machine.start_make("job.nc")
        await state(bench, S.RUN)
        bench.machine.pause()
        bench.machine.resume()  # at once: the board has not even read the `!` yet
        assert bench.machine.current_job().state == "running"  # type: ignore[union-attr]
        done = await bench.job_ended(job.id)
        assert done.state == "completed" and done.lines_acked == 40
        read = b"".join(r.data for r in bench.board.received)  # the raw bytes, as read
        assert read.count(b"~") == 1  # one `~`, written once the hold was complete


async def test_an_override_answers_the_new_values_though_grblhal_reports_first(
    tmp_path: Path,
) -> None:
    """grblHAL over USB answers the `?` behind the override bytes before they act
    (the simulator's `report_first`, its grblHAL default); that report carries the old
    `Ov:` when the board's counter runs out there. The answer is the next one's."""
    async with grbl_bench(tmp_path, HAL) as bench:
        sim = bench.board
        for feed, rapid, spindle in ((150, 25, 80), (60, 100, 120)):
            sim.report_overrides_next()
            got = await operations.override(bench.machine, feed, rapid, spindle)
            assert got == {"feed": feed, "spindle": spindle, "rapid": rapid}
            assert (sim.board.feed_ovr, sim.board.rapid_ovr) == (feed, rapid)
        # The first report after the bytes showed the old values: it was asked again.
        assert any(b"|Ov:100,100,100" in r.data for r in sim.sent)


@pytest.mark.parametrize("streaming", [False, True], ids=["at-rest", "mid-job"])
async def test_a_classic_grbl_override_reaches_the_value_though_alike_bytes_count_once(
    tmp_path: Path, streaming: bool
) -> None:
    """Classic grbl keeps one flag bit per kind of override byte and applies them once a
    main-loop pass (gnea/grbl serial.c:167-181, protocol.c:405-452): a reset and five
    "+10" read together make 110, not 150. The host writes one byte of a kind a round
    and asks, until the board shows what was asked, at rest or while a job streams."""
    slow = GrblConfig(flavour="grbl", speed_factor=5.0, feedhold_decel=0.02)
    async with grbl_bench(tmp_path, slow) as bench:
        job = None
        if streaming:
            # 10 mm moves (0.2 s each here): the planner never runs dry meanwhile.
            bench.write("job.nc", "".join(f"G1 X{i % 2 * 10} F600\n" for i in range(100)))
            job = await bench.machine.start_make("job.nc")
            await bench.board.wait_state("Run")
        got = await operations.override(bench.machine, 150, None, 80)
        assert got == {"feed": 150, "spindle": 80, "rapid": 100}
        board = bench.board.board
        assert (board.feed_ovr, board.rapid_ovr, board.spindle_ovr) == (150, 100, 80)
        got = await operations.override(bench.machine, 11, 50, 199)  # the long ways
        assert got == {"feed": 11, "spindle": 199, "rapid": 50}
        assert (board.feed_ovr, board.rapid_ovr, board.spindle_ovr) == (11, 50, 199)
        if job is not None:
            assert bench.machine.current_job().state == "running"  # type: ignore[union-attr]
            await bench.machine.cancel()
            done = await bench.job_ended(job.id)
            assert done.state == "cancelled"


async def test_a_grblhal_override_of_many_steps_reaches_the_value_though_a_ring_holds_15(
    tmp_path: Path,
) -> None:
    """grblHAL queues override bytes in rings of 16 slots (15 usable; feed and rapid share
    one) and drops a byte that finds its ring full (override.c:35-43, protocol.c:941-960):
    the 19 bytes of 100 to 199 or to 11, read in one USB packet, lost their last ones."""
    async with grbl_bench(tmp_path, HAL) as bench:
        board = bench.board.board
        for feed, rapid, spindle in ((199, 25, 11), (11, 100, 199)):
            got = await operations.override(bench.machine, feed, rapid, spindle)
            assert got == {"feed": feed, "spindle": spindle, "rapid": rapid}
            assert (board.feed_ovr, board.rapid_ovr, board.spindle_ovr) == (feed, rapid, spindle)
        assert board.ovr_dropped == 0


async def test_an_override_takes_no_report_to_an_older_question_for_its_answer(
    tmp_path: Path,
) -> None:
    """A board that reads its input late and in order (grblHAL's upstream Simulator feeds
    its firmware a byte a main-loop pass, behind what came before) answers each `?` the
    heartbeat asked again with a report of its own, after the host wrote an override
    round: those reports predate the round's bytes. Taken for the round's answer, the
    next round stepped again from the old 100: asked 150, the upstream Simulator went to
    200 while the host answered 150 (docs/dialects.md, "Compared against the firmware's
    own simulators")."""
    async with grbl_bench(tmp_path, HAL, heartbeat=0.05, link_silence=60.0) as bench:
        sim = bench.board
        sim.queue_input()
        await sim.wait_for(lambda: (sim.board.queued or b"").count(b"?") >= 3)
        asked = asyncio.create_task(operations.override(bench.machine, 150, None, None))
        await sim.wait_for(lambda: b"\x90\x91\x91\x91\x91\x91?" in (sim.board.queued or b""))
        sim.queue_input(False)
        got = await asked
        assert got == {"feed": 150, "spindle": 100, "rapid": 100}
        assert sim.board.feed_ovr == 150
        read = b"".join(r.data for r in sim.received)
        assert read.count(b"\x91") == 5  # one round: never a step past what was asked


AUTO = GrblConfig(flavour="grblhal", speed_factor=5.0, feedhold_decel=0.02, auto_report=0.05)


def reports_sent(sim: GrblSimController) -> int:
    return sum(r.data.startswith(b"<") for r in sim.sent)


async def test_a_grblhal_that_reports_by_itself_streams_holds_and_overrides_as_asked(
    tmp_path: Path,
) -> None:
    """grblHAL with `$481` set prints a report every interval that no `?` asked for
    (grbllib.c:160-167), and still answers `?` (protocol.c:987-990): the host connects,
    a job streams, holds, resumes and completes, the overrides asked mid-job are the
    ones in force, and the link is never taken for lost."""
    async with grbl_bench(tmp_path, AUTO) as bench:
        sim = bench.board
        bench.write("job.nc", "".join(f"G1 X{i % 2 * 5} F3000\n" for i in range(60)))
        job = await bench.machine.start_make("job.nc")
        await sim.wait_state("Run")
        for feed, spindle in ((173, 57), (100, 100), (11, 199)):
            got = await operations.override(bench.machine, feed, None, spindle)
            assert got == {"feed": feed, "spindle": spindle, "rapid": 100}
            assert (sim.board.feed_ovr, sim.board.spindle_ovr) == (feed, spindle)
        bench.machine.feedhold()
        await state(bench, S.HOLD)
        bench.machine.resume()
        done = await bench.job_ended(job.id)
        assert done.state == "completed" and done.lines_acked == 60
        assert not link_downs(bench)  # never taken for lost
        asked = b"".join(r.data for r in sim.received).count(b"?")
        assert reports_sent(sim) > asked  # the board did report by itself


async def test_an_override_read_late_among_reports_nobody_asked_for_is_never_overshot(
    tmp_path: Path,
) -> None:
    """grblHAL's upstream Simulator with `$481=200`, mid-job: its reports kept coming
    while the host's override bytes waited behind the job's lines (it feeds its firmware
    a byte a pass), and a round that stepped on from such a report took an override
    asked at 173 to 200 and spindle 57 to 14 (docs/dialects.md). Here the bytes wait
    unread until several reports have gone: the board never runs past what was asked,
    and the answer is what it runs."""
    async with grbl_bench(tmp_path, AUTO, heartbeat=5.0, link_silence=60.0) as bench:
        sim = bench.board
        sim.queue_input()
        asked = asyncio.create_task(operations.override(bench.machine, 173, None, 57))
        # The round's resets, feed's and spindle's, wait unread with the rest.
        await sim.wait_for(lambda: {0x90, 0x99} <= set(sim.board.queued or b""))
        held = reports_sent(sim)
        await sim.wait_for(lambda: reports_sent(sim) >= held + 4)
        sim.queue_input(False)
        got = await asked
        assert got == {"feed": 173, "spindle": 57, "rapid": 100}
        assert (sim.board.feed_ovr, sim.board.spindle_ovr) == (173, 57)
        ran = sim.board.overrides_run
        assert max(feed for feed, _, _ in ran) == 173, ran
        assert min(spindle for _, _, spindle in ran) == 57, ran


async def test_a_limit_switch_mid_job_fails_it_and_only_a_reset_then_unlock_clears(
    tmp_path: Path,
) -> None:
    config = GrblConfig(flavour="grbl", speed_factor=5.0, hard_limits=True)
    async with grbl_bench(tmp_path, config) as bench:
        bench.write("job.nc", "".join(f"G1 X{i % 20} F3000\n" for i in range(100)))
        job = await bench.machine.start_make("job.nc")
        await state(bench, S.RUN)
        bench.board.limit_switch("x")
        done = await bench.job_ended(job.id)
        assert done.state == "failed" and done.error is not None
        assert done.error.code == 204 and "Hard limit" in done.error.message
        engine = bench.machine.engine
        with pytest.raises(Rejected) as refused:
            await engine.send("G0 X1")
        assert refused.value.code == 204
        with pytest.raises(Rejected, match="reads nothing until a reset"):
            await engine.clear()
        bench.board.limit_switch("x", active=False)
        await bench.machine.reset()
        assert engine.model.homed is False  # a hard limit loses the position
        await engine.clear()
        await state(bench, S.READY)
        assert (await engine.send("G0 X1")).ok


async def test_estop_is_left_only_by_a_reset(tmp_path: Path) -> None:
    async with grbl_bench(tmp_path, HAL) as bench:
        engine = bench.machine.engine
        bench.board.estop(True)
        await state(bench, S.SHUTDOWN)
        with pytest.raises(Rejected) as refused:
            await engine.clear()
        assert refused.value.code == 205
        bench.board.estop(False)
        await bench.machine.reset()
        await state(bench, S.ALARM)  # grblHAL then asks for `$H` or `$X`
        await engine.clear()
        await state(bench, S.READY)


async def test_a_signal_reads_grbls_pins(tmp_path: Path) -> None:
    signals = {"estop": {"key": "pin_e", "equals": 1}}
    async with grbl_bench(tmp_path, HAL, signals=signals) as bench:
        assert bench.machine.faults.get("estop").active is False
        quiet = await bench.recorder.wait_for(lambda e: isinstance(e, StatusChanged))
        assert quiet.report["pin_e"] == 0  # type: ignore[union-attr]
        bench.board.estop(True)
        pressed = await bench.recorder.wait_for(
            lambda e: isinstance(e, StatusChanged) and e.report.get("pin_e") == 1
        )
        assert pressed.report["pin_x"] == 0  # type: ignore[union-attr]
        assert bench.machine.faults.get("estop").active


async def test_an_open_door_stops_the_stream_and_refuses_lines(tmp_path: Path) -> None:
    slow = GrblConfig(flavour="grbl", speed_factor=5.0, feedhold_decel=0.02)
    async with grbl_bench(tmp_path, slow) as bench:
        bench.write("job.nc", "".join(f"G1 X{i % 20} F3000\n" for i in range(80)))
        job = await bench.machine.start_make("job.nc")
        await state(bench, S.RUN)
        bench.board.door(True)
        await state(bench, S.INTERLOCK)
        assert bench.machine.snapshot()["board_state"].startswith("Door")
        held = bench.machine.current_job()
        assert held is not None and held.state == "running"
        bench.board.door(False)
        bench.machine.engine.realtime(Realtime.CYCLE_START)
        done = await bench.job_ended(job.id)
        assert done.state == "completed" and done.lines_acked == 80


async def test_cancel_holds_then_resets_and_resyncs_without_losing_position(
    tmp_path: Path,
) -> None:
    slow = GrblConfig(flavour="grbl", speed_factor=5.0, feedhold_decel=0.02)
    async with grbl_bench(tmp_path, slow) as bench:
        bench.write("job.nc", "".join(f"G1 X{i % 20} F3000\n" for i in range(80)))
        job = await bench.machine.start_make("job.nc")
        await state(bench, S.RUN)
        await bench.machine.cancel()
        done = await bench.job_ended(job.id)
        assert done.state == "cancelled"
        await bench.supervisor(Sup.IDLE)
        tx = bench.recorder.tx()
        assert tx.index("!") < tx.index("\x18")  # the hold first, the reset at rest
        assert bench.machine.engine.model.state is S.READY  # no ALARM:3: it had stopped
        assert (await bench.machine.engine.send("G0 X1")).ok


async def test_jog_and_jog_cancel(tmp_path: Path) -> None:
    slow = GrblConfig(flavour="grbl", speed_factor=1.0)
    async with grbl_bench(tmp_path, slow) as bench:
        job = await bench.machine.jog({"x": 50.0}, 100.0)
        await state(bench, S.JOG)
        assert any(line.startswith("$J=G91 X50") for line in bench.recorder.tx())
        bench.machine.jog_stop()
        done = await bench.job_ended(job.id)
        assert done.state in ("cancelled", "completed")
        await state(bench, S.READY)
        assert r"\x85" in bench.recorder.tx()  # 0x85, as the console shows a non-UTF-8 byte
        assert bench.machine.engine.model.position["x"] < 50.0


async def test_a_probe_result_reaches_the_snapshot(tmp_path: Path) -> None:
    async with grbl_bench(tmp_path) as bench:
        engine = bench.machine.engine
        send = asyncio.ensure_future(engine.send("G38.2 Z-10 F100"))
        await bench.board.wait_state("Run")
        bench.board.probe(True)
        assert (await send).ok
        probe = bench.machine.snapshot()["probe"]
        assert probe["ok"] is True and probe["position"]["z"] < 0


async def test_check_mode_runs_no_motion_and_reports_errors(tmp_path: Path) -> None:
    async with grbl_bench(tmp_path) as bench:
        engine = bench.machine.engine
        assert (await engine.send("$C")).ok
        await engine.wait_for(lambda: engine.model.board_state == "Check")
        bench.write("bad.nc", "G1 X10 F100\nG1 X20 Q5\nG1 X30\n")
        job = await bench.machine.start_make("bad.nc")
        done = await bench.job_ended(job.id)
        assert done.state == "failed" and done.error is not None
        assert "line 2" in done.error.message and "error:" in done.error.message
        assert bench.board.position["x"] == 0.0


async def test_grblhal_error_latch_fails_the_job_at_the_first_error(tmp_path: Path) -> None:
    async with grbl_bench(tmp_path, HAL) as bench:
        bench.write("bad.nc", "G1 X1 F100\nG1 X2 Q5\nG1 X3\nG1 X4\n")
        job = await bench.machine.start_make("bad.nc")
        done = await bench.job_ended(job.id)
        assert done.state == "failed" and done.error is not None
        assert "line 2" in done.error.message
        await bench.supervisor(Sup.IDLE)
        engine = bench.machine.engine
        assert (await engine.send("G0 X0")).ok  # the latch was cleared by the re-sync


async def test_garbage_from_the_board_is_a_lexical_fault(tmp_path: Path) -> None:
    async with grbl_bench(tmp_path) as bench:
        bench.board.inject_garbage(b"<Idle|MPos\x01:0,0>\r\n")
        await bench.recorder.wait_for(
            lambda e: isinstance(e, FaultChanged) and e.fault["id"] == "lexical"
        )
        with pytest.raises(ControllerError):
            await bench.machine.engine.send("G1 X1 Q5")


async def test_a_reset_mid_job_fails_it_loses_position_and_resyncs(tmp_path: Path) -> None:
    slow = GrblConfig(flavour="grbl", speed_factor=5.0, homing=True)
    async with grbl_bench(tmp_path, slow, idle=False) as bench:
        engine = bench.machine.engine
        assert engine.model.state is S.ALARM  # homing on: '$H'|'$X' to unlock
        assert (await engine.send("$H")).ok
        assert engine.model.homed is True
        await bench.supervisor(Sup.IDLE)
        bench.write("job.nc", "".join(f"G1 X{i % 20} F3000\n" for i in range(80)))
        job = await bench.machine.start_make("job.nc")
        await state(bench, S.RUN)
        await bench.machine.reset()  # 0x18 in motion: grbl says ALARM:3, then its banner
        done = await bench.job_ended(job.id)
        assert done.state == "failed" and done.error is not None
        assert done.error.code == 204 and "in motion" in done.error.message
        assert engine.ready and engine.model.state is S.ALARM
        assert engine.model.homed is False  # the position is no longer known
        assert bench.machine.snapshot()["last_exception"]["alarm"] == 3
        await engine.clear()
        await state(bench, S.READY)


@pytest.mark.parametrize(
    ("flavour", "low"), [("grblhal", (0.0, 200.0)), ("grbl", (-200.0, 0.0))], ids=["hal", "grbl"]
)
async def test_the_travel_is_where_homing_puts_the_origin(
    tmp_path: Path, flavour: str, low: tuple[float, float]
) -> None:
    """grblHAL's `$22` bit 3 ("Set machine origin to 0") puts 0 where each axis homes; an
    axis homing to its low end (`$23`) then runs 0..+travel (machine_limits.c). The
    travel check and the safe height must read it so, or a program inside the machine
    is refused and one past its low end passes. Classic grbl's `$22` is 0 or 1."""
    config = GrblConfig(flavour=flavour, speed_factor=50.0, homing=True)
    async with grbl_bench(tmp_path, config, idle=False) as bench:
        engine = bench.machine.engine
        assert (await engine.send("$X")).ok
        await state(bench, S.READY)
        for line in ("$22=9", "$23=3", "$20=1"):  # X and Y home low; soft limits on
            assert (await engine.send(line)).ok
        assert (await engine.send("$H")).ok
        await bench.supervisor(Sup.IDLE)
        limits = await bench.machine.known_limits()
        assert limits is not None
        assert limits.travel["x"] == limits.travel["y"] == low
        assert limits.travel["z"] == (-200.0, 0.0)  # homes high: as before
        # The board's own soft limits agree: the move the check allows is run.
        inside = 50.0 if low[0] == 0.0 else -50.0
        assert (await engine.send(f"G90 G0 X{inside}")).ok
        async with asyncio.timeout(5):
            await engine.wait_for(lambda: engine.model.machine_position.get("x") == inside)
        assert engine.model.state is not S.ALARM  # no soft limit tripped


# --- a live board is never given up; a gone one is (issue 25) -----------------------

# Quick timings, so that the silences below outlast them several times over.
LIVENESS = {"heartbeat": 0.05, "link_silence": 0.3}


def link_downs(bench: GrblBench) -> list[LinkChanged]:
    return [e for e in bench.recorder.events if isinstance(e, LinkChanged) and not e.up]


async def status_requests(bench: GrblBench, count: int) -> None:
    """Until the engine has written `count` more `?`s from now."""
    start = len(bench.recorder.events)

    def enough(_: object) -> bool:
        sent = bench.recorder.events[start:]
        return (
            sum(isinstance(e, Console) and e.direction == "tx" and e.text == "?" for e in sent)
            >= count
        )

    await bench.recorder.wait_for(enough)


def moves(count: int) -> str:
    return "G21 G90\n" + "".join(f"G1 X{(i % 2) * 10} F3000\n" for i in range(count))


async def test_a_job_runs_on_through_status_requests_lost_on_the_wire(tmp_path: Path) -> None:
    slow = GrblConfig(flavour="grbl", speed_factor=5.0)
    async with grbl_bench(tmp_path, slow, **LIVENESS) as bench:
        bench.write("job.nc", moves(30))
        job = await bench.machine.start_make("job.nc")
        await state(bench, S.RUN)
        bench.board.lose_status_requests(3)
        done = await bench.job_ended(job.id)
        assert done.state == "completed" and done.lines_acked == 31
        assert bench.board.board.status_lost == 0  # all three were lost
        assert link_downs(bench) == []


async def test_a_job_runs_on_while_the_board_answers_lines_but_no_status_request(
    tmp_path: Path,
) -> None:
    slow = GrblConfig(flavour="grbl", speed_factor=5.0)
    async with grbl_bench(tmp_path, slow, **LIVENESS) as bench:
        bench.write("job.nc", moves(40))
        job = await bench.machine.start_make("job.nc")
        await state(bench, S.RUN)
        bench.board.ignore_status_requests()
        await status_requests(bench, 10)  # half a second without a report: past link_silence
        assert bench.machine.engine.ready and link_downs(bench) == []
        bench.board.ignore_status_requests(False)
        done = await bench.job_ended(job.id)
        assert done.state == "completed" and done.lines_acked == 41
        assert link_downs(bench) == []


@pytest.mark.parametrize(
    "config",
    [
        GrblConfig(flavour="grbl", homing=True, homing_time=30.0, speed_factor=30.0),
        GrblConfig(
            flavour="grblhal",
            homing=True,
            homing_time=30.0,
            speed_factor=30.0,
            hal_home_report=False,
        ),
    ],
    ids=["grbl", "grblhal-no-home-report"],
)
async def test_a_30_s_homing_cycle_completes_though_the_board_is_silent_all_along(
    tmp_path: Path, config: GrblConfig
) -> None:
    # 30 s on the machine, 1 s here: over three times link_silence without a byte.
    async with grbl_bench(tmp_path, config, idle=False, **LIVENESS) as bench:
        engine = bench.machine.engine
        assert (await engine.send("$H", timeout=10)).ok
        assert engine.model.homed is True
        await bench.supervisor(Sup.IDLE)
        assert link_downs(bench) == [] and bench.board.opens == 1


async def test_a_job_that_homes_first_runs_on_through_the_cycle(tmp_path: Path) -> None:
    config = GrblConfig(flavour="grbl", homing=True, homing_time=30.0, speed_factor=30.0)
    async with grbl_bench(tmp_path, config, idle=False, **LIVENESS) as bench:
        engine = bench.machine.engine
        await engine.clear()  # `$X`: a job may start
        await bench.supervisor(Sup.IDLE)
        bench.write(
            "job.nc", "$H\nG21 G90\n" + "".join(f"G1 X-{i % 5 + 1} F3000\n" for i in range(20))
        )
        job = await bench.machine.start_make("job.nc")
        done = await bench.job_ended(job.id)
        assert done.state == "completed" and done.lines_acked == 22
        assert engine.model.homed is True and link_downs(bench) == []


async def test_settings_go_one_at_a_time_to_a_board_deaf_while_it_writes_eeprom(
    tmp_path: Path,
) -> None:
    config = GrblConfig(flavour="grbl", speed_factor=50.0, storage_write=0.4)
    async with grbl_bench(tmp_path, config, **LIVENESS) as bench:
        engine = bench.machine.engine
        answers = await asyncio.gather(*(engine.send(f"$11{i}=600") for i in range(3)))
        assert all(a.ok for a in answers)
        assert [bench.board.board.settings[110 + i] for i in range(3)] == [600.0] * 3
        assert link_downs(bench) == []  # 1.2 s of writing, each longer than link_silence


async def test_a_board_that_hangs_mid_job_is_given_up_and_not_reopened_on_its_own(
    tmp_path: Path,
) -> None:
    slow = GrblConfig(flavour="grbl", speed_factor=2.0)
    async with grbl_bench(tmp_path, slow, auto_connect=True, **LIVENESS) as bench:
        bench.write("job.nc", moves(40))
        job = await bench.machine.start_make("job.nc")
        await state(bench, S.RUN)
        bench.board.hang()
        done = await bench.job_ended(job.id)
        assert done.state == "interrupted" and done.error is not None
        assert "silent" in done.error.message
        (down,) = link_downs(bench)
        assert "not reopened" in down.reason
        engine = bench.machine.engine
        assert not engine._want.is_set()  # waiting for machine.connect, though auto_connect
        assert bench.board.opens == 1
        bench.board.hang(False)
        await bench.machine.connect()  # asked for: the port is opened again
        assert engine.ready and bench.board.opens == 2


async def test_a_board_unplugged_mid_job_is_detected_at_once(tmp_path: Path) -> None:
    slow = GrblConfig(flavour="grbl", speed_factor=2.0)
    async with grbl_bench(tmp_path, slow, heartbeat=1.0, link_silence=60.0) as bench:
        bench.write("job.nc", moves(40))
        job = await bench.machine.start_make("job.nc")
        await state(bench, S.RUN)
        await bench.board.unplug()
        done = await bench.job_ended(job.id)
        assert done.state == "interrupted"
        assert len(link_downs(bench)) == 1
        assert "silent" not in link_downs(bench)[0].reason  # the OS said so, not a timeout


async def test_grblhal_snapshot_reads_the_coordinate_system_not_scaling(tmp_path: Path) -> None:
    async with grbl_bench(tmp_path, HAL) as bench:
        assert bench.machine.snapshot()["wcs"] == "G54"  # `[GC:..G98 G50 ..]`: G50 is scaling
        engine = bench.machine.engine
        await engine.send("G55")
        await engine.send("$G")
        assert bench.machine.snapshot()["wcs"] == "G55"


def realtime_and_yields(bench: GrblBench, monkeypatch: pytest.MonkeyPatch) -> list[bytes]:
    """Every realtime byte the link writes from now on, and `yield` where the CPU is
    handed over (`os.sched_yield`), in order."""
    link = bench.machine.engine.link
    assert link is not None
    log: list[bytes] = []
    write_realtime = link.write_realtime

    def recorded(data: bytes) -> bool:
        log.append(data)
        return write_realtime(data)

    monkeypatch.setattr(link, "write_realtime", recorded)
    monkeypatch.setattr(os, "sched_yield", lambda: log.append(b"yield"))
    return log


async def test_an_operators_realtime_byte_hands_the_cpu_over_and_a_status_poll_does_not(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On a pty the board's process reads a `!` only once it gets a CPU: the daemon gives
    its up right after writing the operator's byte (a hold, a job's pause and resume,
    an override), before what the byte sets off. Its own `?` polls never do."""
    slow = GrblConfig(flavour="grbl", speed_factor=5.0, feedhold_decel=0.02)
    async with grbl_bench(tmp_path, slow) as bench:
        log = realtime_and_yields(bench, monkeypatch)
        bench.write("job.nc", "".join(f"G1 X{i % 20} F3000\n" for i in range(60)))
        job = await bench.machine.start_make("job.nc")
        await state(bench, S.RUN)
        bench.machine.feedhold()  # the job's pause
        await state(bench, S.HOLD)
        # The hold complete, so that the resume's `~` goes at once, from the request: while
        # the board still decelerates (Hold:1) the session keeps it back and asks `?`
        # (grbl/holds.py), the next test's case.
        engine = bench.machine.engine
        async with asyncio.timeout(5):
            await engine.wait_for(lambda: engine.model.board_state == "Hold:0")
        await operations.override(bench.machine, 120, None, None)
        bench.machine.cycle_start()  # the job's resume
        done = await bench.job_ended(job.id)
        assert done.state == "completed"
        assert b"?" in log and b"!" in log and b"~" in log
        assert len([byte for byte in log if byte == b"yield"]) >= 3  # `!`, the override, `~`
        after = {log[i - 1] for i, byte in enumerate(log) if byte == b"yield"}
        assert after and b"?" not in after  # each yield follows an operator's byte
        assert log[log.index(b"!") + 1] == b"yield"
        assert log[log.index(b"~") + 1] == b"yield"
        assert all(log[i + 1] != b"yield" for i, byte in enumerate(log[:-1]) if byte == b"?")


async def test_a_resume_kept_back_until_the_board_stands_still_hands_the_cpu_over_as_it_goes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A `~` asked while the board still decelerates (Hold:1) is kept back and goes from
    the read of the report that says Hold:0 (grbl/holds.py): that byte is the operator's
    too, and the CPU is handed over after it, not after the `?` asked meanwhile."""
    # Moves long enough that a hold decelerates the whole `feedhold_decel` (one near its
    # end would stop at the end of the move, at once: sim/motion.py `begin_hold`).
    slow = GrblConfig(flavour="grbl", feedhold_decel=0.3)
    async with grbl_bench(tmp_path, slow) as bench:
        engine = bench.machine.engine
        log = realtime_and_yields(bench, monkeypatch)
        bench.write("job.nc", "G1 X60 F6000\nG1 X0\nG1 X60\n")  # 0.6 s a move
        job = await bench.machine.start_make("job.nc")
        await state(bench, S.RUN)
        bench.machine.feedhold()
        async with asyncio.timeout(5):
            await engine.wait_for(lambda: engine.model.board_state == "Hold:1")
        asked = len(log)
        bench.machine.cycle_start()
        assert b"~" not in log[asked:]  # kept back: the board still stops
        async with asyncio.timeout(5):
            await engine.wait_for(lambda: b"~" in log[asked:])
        done = await bench.job_ended(job.id)
        assert done.state == "completed"
        kept = asked + log[asked:].index(b"~")
        assert log[kept + 1] == b"yield"
        assert all(log[i + 1] != b"yield" for i, byte in enumerate(log[:-1]) if byte == b"?")
