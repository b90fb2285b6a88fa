"""Holds, client lines admitted at the moment they are written, and a job's final end.

Every assertion is on what the simulated board read over the pty
(`sim.received`), on the job rows in SQLite, or on what a caller was told.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
from dataclasses import replace
from pathlib import Path

import pytest

from hostd.machine.events import Console, Event, StatusChanged, SupervisorChanged
from hostd.machine.supervisor import State as Sup
from hostd.protocol.commands import Realtime
from hostd.protocol.errors import Busy, MachineError
from hostd.protocol.states import MachineState as S
from hostd.sim import SimController
from tests.machine.conftest import FAST, Bench, Rig, bench_for, long_moves

pytestmark = pytest.mark.asyncio

LONG = "".join(f"G1 X{(i % 2) * 40} F600\n" for i in range(300))
SHORT = "G21 G90\nG1 X2 F3000\nG1 X0\n"


async def held(bench: Bench) -> None:
    """Until the daemon has read that the board holds (not only until the board does)."""
    engine = bench.machine.engine
    await engine.wait_for(lambda: engine.model.state is S.HOLD)


def lines_between(sim: SimController, first: bytes, last: bytes | None) -> list[bytes]:
    """The lines the board read after the first `first` byte and before the next `last`."""
    out: list[bytes] = []
    inside = False
    for r in sim.received:
        if r.data == first and not inside:
            inside = True
        elif inside and last is not None and r.data == last:
            break
        elif inside and r.kind == "line":
            out.append(r.data)
    return out


async def test_a_paused_job_writes_none_of_its_lines_until_resumed(bench: Bench) -> None:
    bench.write("long.gcode", LONG)
    job = await bench.machine.start_make("long.gcode")
    await bench.sim.wait_state(S.RUN)
    bench.machine.pause()
    await held(bench)
    # A round trip through the board: everything written before it has been read.
    await bench.machine.engine.send("{xvm:n}")
    await bench.machine.engine.send("{yvm:n}")
    read_in_hold = lines_between(bench.sim, b"!", None)
    assert read_in_hold == [b'{"xvm":null}', b'{"yvm":null}']  # queries only, no job line
    assert bench.machine.current_job() is not None
    assert bench.machine.current_job().state == "paused"  # type: ignore[union-attr]
    bench.machine.resume()
    await bench.sim.wait_for(lambda: len(lines_between(bench.sim, b"~", None)) > 4)
    bench.machine.jog_stop()
    assert (await bench.job_ended(job.id)).state == "cancelled"


async def test_a_resume_the_board_never_held_for_writes_no_job_line_while_still_paused(
    tmp_path: Path,
) -> None:
    # Moves in real time (speed_factor 1, ~85 ms a line), not FAST's fiftieth: the
    # resumed job must not underflow because a loaded test machine was late to refill.
    board = replace(FAST, fb=101.03, speed_factor=1.0)
    async with bench_for(tmp_path, sim_config=board) as bench:
        await _a_resume_the_board_never_held_for(bench)


async def _a_resume_the_board_never_held_for(bench: Bench) -> None:
    """A pause the board ignored (nothing moving): the resume's lines follow `operation`.

    Only a board before 101.05 ignores a `!` with nothing moving (g2builds.py):
    101.06 holds at rest, and never lets this happen.

    The job's first window and the pause's `!` are written in one step, so the
    board reads them in one read, before it runs anything: the `!` finds nothing
    moving and is ignored. The board runs the window and stops, and the host reads
    every answer. The resume then has room and no hold to wait for: its `~` and
    the job's next lines go out at once, and not one of those lines may be
    written while the supervisor still says `paused` (Machine.resume moves the
    supervisor in the engine's one step, whose writes go out at its end).
    Every write is judged as it is published, against the supervisor's state
    at that very moment (publishing is synchronous).
    """
    machine, engine = bench.machine, bench.machine.engine
    engine.console = True  # every line written is published in the step that writes it
    job_line = re.compile(r"N(\d+) G1 X\d+ Y\d+ F1000")
    written: list[tuple[int, str]] = []  # (file line written, the supervisor's state then)

    def observe(event: Event) -> None:
        if isinstance(event, Console) and event.direction == "tx":
            line = job_line.fullmatch(event.text)
            if line is not None:
                written.append((int(line.group(1)), machine.supervisor.state.value))

    machine.hub.subscribe(observe)
    bench.write("steps.gcode", "".join(f"G1 X{i % 2 + 1} Y{i} F1000\n" for i in range(12)))
    job = await machine.start_make("steps.gcode")
    machine.pause()  # no await since the window was written: the board reads both together
    window = len(written)
    assert written == [(n, "operation") for n in range(1, window + 1)] and window > 0

    # The board ran the window and stopped without a hold; the host read all of it.
    ran = False

    def stopped_after_running(event: Event) -> bool:
        nonlocal ran
        if not isinstance(event, StatusChanged):
            return False
        ran = ran or event.report.get("stat") == S.RUN
        return ran and event.report.get("stat") == S.PROGRAM_STOP

    await bench.recorder.wait_for(stopped_after_running)
    await engine.wait_for(engine.session.no_data_in_flight)
    assert [r.data for r in bench.sim.received if r.kind == "realtime"] == [b"!"]
    assert not any(
        isinstance(e, StatusChanged) and e.report.get("stat") == S.HOLD
        for e in bench.recorder.events
    ), "the board held: this test needs a pause it ignored"
    assert engine.model.state is S.PROGRAM_STOP and machine.supervisor.state is Sup.PAUSED
    assert len(written) == window  # nothing written while paused, so far

    machine.resume()
    resumed = written[window:]
    assert resumed, "the resume wrote no job line at once: the window had no room?"
    while_paused = [n for n, state in resumed if state != "operation"]
    assert not while_paused, f"file lines {while_paused} written while the job is paused"
    assert [n for n, _ in resumed] == list(range(window + 1, window + 1 + len(resumed)))
    assert bench.transitions()[-2:] == [
        ("operation", "pause-operation", "paused"),
        ("paused", "unpause-operation", "operation"),
    ]
    assert (await bench.job_ended(job.id)).state == "completed"
    assert [n for n, _ in written] == list(range(1, 13))
    assert {state for _, state in written} == {"operation"}


async def test_a_line_sent_in_a_pause_runs_inside_the_hold_at_once(bench: Bench) -> None:
    bench.write("long.gcode", LONG)
    await bench.machine.start_make("long.gcode")
    await bench.sim.wait_state(S.RUN)
    bench.machine.pause()
    await held(bench)
    # The board keeps the job's lines in flight for after the hold, unanswered:
    # the in-hold line must not wait behind them.
    bench.sim.set_ack_delay(30)
    response = await bench.machine.engine.send("G91 G0 Z1", timeout=2)
    assert response.ok
    assert b'{"gc2":"G91 G0 Z1"}' in lines_between(bench.sim, b"!", None)
    assert not any(r.data == b"~" for r in bench.sim.received)


async def test_a_text_setting_in_a_hold_is_refused_not_left_for_after_it(bench: Bench) -> None:
    bench.write("long.gcode", LONG)
    await bench.machine.start_make("long.gcode")
    await bench.sim.wait_state(S.RUN)
    bench.machine.pause()
    await held(bench)
    before = len(bench.sim.received)
    with pytest.raises(Busy, match="send settings as JSON"):
        await bench.machine.engine.send("$xvm=1000")
    await bench.machine.engine.send("{xvm:n}")
    assert [r.data for r in bench.sim.received[before:]] == [b'{"xvm":null}']


async def test_an_action_while_the_job_is_still_entering_its_hold_is_refused(
    bench: Bench,
) -> None:
    bench.write("long.gcode", LONG)
    await bench.machine.start_make("long.gcode")
    await bench.sim.wait_state(S.RUN)
    bench.machine.pause()  # the board is still decelerating: not yet in HOLD
    with pytest.raises(Busy, match="still entering its hold"):
        await bench.machine.engine.send("G0 Z1")


async def test_a_waiting_line_fails_when_a_job_starts_instead_of_running_inside_it(
    rig: Rig,
) -> None:
    rig.sim.set_ack_delay(30)  # the board reads on but answers nothing for now
    engine = rig.engine
    before = len(rig.received_lines())
    first = [asyncio.create_task(engine.send(f"G0 X{i}", timeout=60)) for i in range(4)]
    late = asyncio.create_task(engine.send("G0 Y9", timeout=60))
    await rig.sim.wait_received(lambda: len(rig.received_lines()) >= before + 4)
    assert not late.done()  # the window is full: it waits on the host
    rig.job(["G1 X1 F600"])
    with pytest.raises(Busy, match="an operation started before the line was written"):
        await late
    assert b"G0 Y9" not in rig.received_lines()
    for task in first:
        task.cancel()
    await asyncio.gather(*first, return_exceptions=True)


async def test_a_waiting_line_fails_when_a_hold_begins(rig: Rig) -> None:
    rig.sim.set_ack_delay(30)
    engine = rig.engine
    moves = [asyncio.create_task(engine.send(f"G1 X{10 * i} F300", timeout=60)) for i in (1, 2)]
    moves += [asyncio.create_task(engine.send(f"G1 Y{i} F300", timeout=60)) for i in (1, 2)]
    late = asyncio.create_task(engine.send("G0 Z9", timeout=60))
    await rig.sim.wait_state(S.RUN)
    assert not late.done()
    engine.realtime(Realtime.FEEDHOLD)
    # Written after the hold it would be kept by the board and run after `~`.
    with pytest.raises(Busy, match="a hold began before the line was written"):
        await late
    assert b"G0 Z9" not in rig.received_lines()
    for task in moves:
        task.cancel()
    await asyncio.gather(*moves, return_exceptions=True)


async def test_queries_have_a_bounded_lane_and_realtime_goes_ahead_of_them(rig: Rig) -> None:
    engine = rig.engine
    rig.job([f"G1 X{i % 2 * 20} F3000" for i in range(200)])
    await rig.sim.wait_state(S.RUN)
    start = len(rig.sim.received)
    flood = [asyncio.create_task(engine.send("{sr:n}")) for _ in range(200)]
    await asyncio.sleep(0)  # every request has arrived and queued
    engine.realtime(Realtime.FEEDHOLD)
    await rig.sim.wait_received(b"!")
    before_bang = [r.data for r in rig.sim.received[start:]]
    before_bang = before_bang[: before_bang.index(b"!")]
    # At most the lane's four queries reached the board ahead of the `!`.
    assert before_bang.count(b'{"sr":null}') <= 4
    answers = await asyncio.gather(*flood)
    assert all(a.ok for a in answers)
    assert rig.recorder.max_in_flight() <= 4 + 4 + 1  # window, lane, and one own probe


async def test_a_query_flood_does_not_starve_a_running_job(bench: Bench) -> None:
    # 40 mm a line (~16 ms on FAST's board): the job runs dry only if the flood holds its
    # lines back for several of them, not because a loaded test machine ran late once.
    bench.write("part.gcode", "".join(f"{line}\n" for line in long_moves(60, feed=3000)))
    job = await bench.machine.start_make("part.gcode")

    async def flood() -> None:
        while True:
            await asyncio.gather(*(bench.machine.engine.send("{sr:n}") for _ in range(20)))

    flooding = asyncio.create_task(flood())
    try:
        row = await bench.job_ended(job.id)
    finally:
        flooding.cancel()
        with contextlib.suppress(asyncio.CancelledError, MachineError):
            await flooding
    assert (row.state, row.lines_acked) == ("completed", 60)
    assert not [f for f in bench.machine.faults.active() if f.id == "underflow"]


# -- a job's end is final ----------------------------------------------------


async def test_pause_resume_and_cancel_after_the_end_are_refused(bench: Bench) -> None:
    bench.write("short.gcode", SHORT)
    job = await bench.machine.start_make("short.gcode")
    assert (await bench.job_ended(job.id)).state == "completed"
    for act in (bench.machine.pause, bench.machine.resume):
        with pytest.raises(Busy):
            act()
    with pytest.raises(Busy):
        await bench.machine.cancel()
    row = await bench.store.get(job.id)
    assert row is not None and row.state == "completed"


async def test_a_pause_as_the_stream_ends_leaves_the_job_completed(bench: Bench) -> None:
    bench.write("short.gcode", SHORT)
    job = await bench.machine.start_make("short.gcode")
    stream = bench.machine.jobs.stream
    assert stream is not None
    outcomes: list[str] = []

    def pause_now(_: object) -> None:  # the instant the stream ends, before its row is written
        try:
            bench.machine.pause()
            outcomes.append("paused")
        except Busy as exc:
            outcomes.append(f"refused {exc.code}")

    stream.result.add_done_callback(pause_now)
    row = await bench.job_ended(job.id)
    assert outcomes == ["refused 1003"]
    assert (row.state, row.ended_at is not None) == ("completed", True)
    await bench.supervisor(Sup.IDLE)
    assert bench.machine.current_job().state == "completed"  # type: ignore[union-attr]


async def test_a_pause_while_the_next_job_starts_leaves_the_last_one_completed(
    bench: Bench,
) -> None:
    bench.write("short.gcode", SHORT)
    first = await bench.machine.start_make("short.gcode")
    assert (await bench.job_ended(first.id)).state == "completed"
    await bench.supervisor(Sup.IDLE)
    outcomes: list[str] = []

    def pause_at_start(event: Event) -> None:
        # The supervisor has gone to `operation`; the new row is being written.
        if isinstance(event, SupervisorChanged) and event.target == "operation":
            try:
                bench.machine.pause()
                outcomes.append("paused")
            except Busy:
                outcomes.append("refused")

    bench.machine.hub.subscribe(pause_at_start)
    second = await bench.machine.start_make("short.gcode")
    assert outcomes == ["refused"]
    row = await bench.store.get(first.id)
    assert row is not None and row.state == "completed"
    assert (await bench.job_ended(second.id)).state == "completed"


# -- settings --------------------------------------------------------------


async def test_settings_are_read_in_an_alarm_without_a_job_row(bench: Bench) -> None:
    bench.sim.limit_switch("x")
    await bench.sim.wait_state(S.ALARM)
    await bench.machine.engine.wait_for(lambda: bench.machine.engine.model.state is S.ALARM)
    jobs_before = await bench.store.list_jobs("m1", 50)
    assert await bench.machine.read_settings(["xvm", "yvm"]) == {"xvm": 6000, "yvm": 6000}
    assert await bench.store.list_jobs("m1", 50) == jobs_before


async def test_an_abandoned_settings_operation_is_recorded_failed(bench: Bench) -> None:
    bench.sim.set_ack_delay(30)
    task = asyncio.create_task(bench.machine.settings(['{"xvm":12000}']))
    await bench.sim.wait_received(b'{"xvm":12000}')
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    job = bench.machine.job
    assert job is not None and job.kind == "settings"
    row = await bench.store.get(job.id)
    assert row is not None and row.state == "failed"


async def test_a_query_is_answered_while_a_flush_is_unconfirmed(rig: Rig) -> None:
    # `%` outside a hold: the board ignores it, and the engine waits up to 2 s to
    # see whether it flushed. Queries are `{`-lines the board runs at once anyway.
    rig.engine.realtime(Realtime.QUEUE_FLUSH)
    response = await rig.engine.send("{xvm:n}")
    assert response.body == {"xvm": 6000}
    assert rig.engine.session.flushing()  # answered before the flush was settled


async def test_a_probe_failure_report_mid_job_stops_the_job_as_an_alarm(bench: Bench) -> None:
    # A G38.2 that never touches: cycle_probing.cpp cm_alarm(STAT_PROBE_CYCLE_FAILED, ...).
    bench.write("long.gcode", "G1 X10 F600\nG38.2 Z-2 F3000\n" + LONG)
    job = await bench.machine.start_make("long.gcode")
    row = await bench.job_ended(job.id)
    assert any(b'"st":250' in s.data for s in bench.sim.sent)
    assert (row.state, row.error is not None and row.error.code) == ("failed", 204)
    assert row.lines_acked < 300


async def test_a_client_action_during_a_settings_operation_is_busy(bench: Bench) -> None:
    bench.sim.set_ack_delay(0.3)  # the operation's line waits for its answer
    operation = asyncio.create_task(bench.machine.settings(['{"xvm":7000}']))
    await bench.sim.wait_received(b'{"xvm":7000}')
    before = len(bench.sim.received)
    with pytest.raises(Busy, match="running an operation"):
        await bench.machine.engine.send("G0 Z1")
    job, _ = await operation
    assert b"G0 Z1" not in [r.data for r in bench.sim.received[before:]]
    row = await bench.store.get(job.id)
    assert row is not None and row.state == "completed"
