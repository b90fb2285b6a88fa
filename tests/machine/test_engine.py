"""The engine against the simulated board, over real pseudo-terminals.

Assertions are on what the board actually received (`sim.received`) and on
the engine's own ordered event stream (`Recorder`).
"""

from __future__ import annotations

import asyncio
import dataclasses
import os
from pathlib import Path

import pytest

from hostd.link import Channel, Link
from hostd.machine.engine import Engine, LinkState
from hostd.machine.events import (
    Console,
    ExceptionRaised,
    FaultDetected,
    LinkChanged,
    StatusChanged,
)
from hostd.machine.stream import JobStream
from hostd.protocol.commands import InvalidCommand, Realtime
from hostd.protocol.errors import Busy, ControllerError, NotConnected, Rejected
from hostd.protocol.program import program_lines
from hostd.protocol.states import MachineState as S
from hostd.protocol.vocabulary import StreamEnd
from hostd.sim import SimConfig, SimController
from tests.machine.conftest import FAST, Recorder, Rig, machine_config, running

pytestmark = pytest.mark.asyncio


def moves(count: int, feed: int = 3000, step: float = 4.0) -> list[str]:
    return [f"G1 X{(i % 50) * step:.3f} Y{(i % 7) * step:.3f} F{feed}" for i in range(1, count + 1)]


async def state(rig: Rig, want: S) -> None:
    await rig.sim.wait_state(want)
    async with asyncio.timeout(2):
        await rig.engine.wait_for(lambda: rig.engine.model.state is want)


def status_requests(rig: Rig) -> int:
    return sum(r.data == b'{"sr":null}' for r in rig.sim.received)


async def lock(rig: Rig, kind: S) -> None:
    asked = status_requests(rig)
    if kind is S.ALARM:
        rig.sim.limit_switch("x")
    elif kind is S.SHUTDOWN:
        rig.sim.estop(True)
    else:
        rig.sim.panic()
    await state(rig, kind)
    # The exception report made the engine ask where the board is: let that settle.
    await rig.sim.wait_for(lambda: status_requests(rig) > asked)


async def finished(stream: JobStream) -> None:
    async with asyncio.timeout(10):
        await stream.result


# -- handshake and plain requests -------------------------------------------


async def test_handshake_sets_the_board_up_and_reads_its_state(rig: Rig) -> None:
    lines = rig.received_lines()
    assert lines[:3] == [b'{"spc":null}', b'{"ej":1}', b'{"jv":4}']
    (report_list,) = [line for line in lines if line.startswith(b'{"sr":{"stat":true')]
    assert b'"spc":true,"sps":true' in report_list  # the sim's build (101.06) has them
    assert lines[-1] == b'{"sr":null}'
    assert rig.engine.ready
    assert rig.engine.model.state is S.READY


async def test_a_client_line_resolves_with_the_boards_answer(rig: Rig) -> None:
    response = await rig.engine.send("{xvm:n}")
    assert response.ok and "xvm" in response.body
    assert (await rig.engine.send("G0 X5")).ok
    await state(rig, S.PROGRAM_STOP)
    assert rig.sim.position["x"] == pytest.approx(5.0)


async def test_text_queries_go_as_json_gets(rig: Rig) -> None:
    await rig.engine.send("$xvm")
    await rig.engine.send("?")
    assert rig.received_lines()[-2:] == [b'{"xvm":null}', b'{"sr":null}']


async def test_a_refused_gcode_line_is_a_controller_error(rig: Rig) -> None:
    with pytest.raises(ControllerError) as err:
        await rig.engine.send("G5 X1")
    assert err.value.code == 1005
    assert err.value.data["status"] == err.value.status != 0


@pytest.mark.parametrize("line", ["G1 X1\x00", "G1 X" + "9" * 600, "$$", "{m:n}", "", "%"])
async def test_bad_client_lines_are_refused_and_nothing_is_written(rig: Rig, line: str) -> None:
    before = len(rig.sim.received)
    with pytest.raises(InvalidCommand):
        await rig.engine.send(line)
    assert len(rig.sim.received) == before
    assert (await rig.engine.send("{xvm:n}")).ok  # and the machine is fine


# -- the command class table, in every lockout ------------------------------

ROWS = [  # line, refused with (ALARM, SHUTDOWN, PANIC)
    ("{xvm:n}", (None, None, None)),
    ("$xvm", (None, None, None)),
    ("G0 X1", (204, 205, 206)),
    ("{xvm:16000}", (204, 205, 206)),
    ("$xvm=16000", (204, 205, 206)),
    ("{clear:1}", (204, 205, 206)),
]


@pytest.mark.parametrize("kind", [S.ALARM, S.SHUTDOWN, S.PANIC])
async def test_class_table_rows_in_each_lockout(rig: Rig, kind: S) -> None:
    await lock(rig, kind)
    column = {S.ALARM: 0, S.SHUTDOWN: 1, S.PANIC: 2}[kind]
    for line, refusals in ROWS:
        before = len(rig.sim.received)
        refusal = refusals[column]
        if refusal is None:
            await rig.engine.send(line)
            assert len(rig.sim.received) == before + 1, line
        else:
            with pytest.raises(Rejected) as err:
                await rig.engine.send(line)
            assert err.value.code == refusal, line
            assert len(rig.sim.received) == before, f"{line!r} reached the board"
    # Realtime: `!` always goes, `~` never in a lockout.
    rig.engine.realtime(Realtime.FEEDHOLD)
    with pytest.raises(Rejected):
        rig.engine.realtime(Realtime.CYCLE_START)
    await rig.sim.wait_received(lambda: rig.sim.received[-1].data == b"!")
    assert not any(r.data == b"~" for r in rig.sim.received)


async def test_m30_clears_an_alarm(rig: Rig) -> None:
    await lock(rig, S.ALARM)
    await rig.engine.send("M30")
    await rig.sim.wait_for(lambda: not rig.sim.state.is_lockout)
    assert b"M30" in rig.received_lines()


async def test_m30_is_refused_in_shutdown_and_never_sent(rig: Rig) -> None:
    await lock(rig, S.SHUTDOWN)
    with pytest.raises(Rejected) as err:
        await rig.engine.send("M30")
    assert err.value.code == 205
    assert b"M30" not in rig.received_lines()


async def test_clear_leaves_alarm_on_the_data_port(rig: Rig) -> None:
    await lock(rig, S.ALARM)
    assert rig.engine.model.homed is False
    await rig.engine.clear()
    assert rig.engine.model.state is not None and not rig.engine.model.state.is_lockout
    assert rig.received_lines()[-1] == b'{"clear":null}'


async def test_clear_leaves_shutdown_once_the_estop_is_released(rig: Rig) -> None:
    await lock(rig, S.SHUTDOWN)
    rig.sim.estop(False)
    await rig.engine.clear()
    assert rig.engine.model.state in (S.PROGRAM_STOP, S.PROGRAM_END)


async def test_clear_outside_a_lockout_sends_nothing(rig: Rig) -> None:
    before = len(rig.sim.received)
    await rig.engine.clear()
    assert len(rig.sim.received) == before


async def test_panic_is_left_only_by_reset(rig: Rig) -> None:
    await lock(rig, S.PANIC)
    with pytest.raises(Rejected) as err:
        await rig.engine.clear()
    assert err.value.code == 206
    with pytest.raises(Rejected):
        await rig.engine.send("M30")
    assert not any(line in rig.received_lines() for line in (b"M30", b'{"clear":null}'))
    await rig.engine.reset()
    assert rig.engine.ready
    assert rig.engine.model.state is S.READY
    assert any(r.data == b"\x18" for r in rig.sim.received)


# -- streaming ----------------------------------------------------------------


async def test_a_job_streams_within_the_window_and_completes(rig: Rig) -> None:
    rig.sim.set_ack_delay(0.002)
    stream = rig.job(["(header)", "G21 G90", *moves(60), "M30"])
    await finished(stream)
    result = stream.result.result()
    assert result.end is StreamEnd.COMPLETED
    assert stream.sent == stream.acked == 62
    assert rig.recorder.max_in_flight() == 4  # the window is used, never exceeded
    job_lines = [line for line in rig.received_lines() if not line.startswith(b"{")]
    assert job_lines[0] == b"G21 G90" and job_lines[-1] == b"M30"
    assert len(job_lines) == 62


async def test_a_query_does_not_wait_behind_job_lines(rig: Rig) -> None:
    stream = rig.job(moves(40, feed=300))  # slow moves fill the planner
    await rig.sim.wait_for(lambda: rig.sim.planner_len > 0)
    response = await asyncio.wait_for(rig.engine.send("{sr:n}"), 0.5)
    assert response.status_report is not None
    assert not stream.done


async def test_action_lines_during_a_job_are_busy(rig: Rig) -> None:
    stream = rig.job(moves(40, feed=300))
    with pytest.raises(Busy):
        await rig.engine.send("G0 X0")
    with pytest.raises(Busy):
        rig.engine.start_stream(JobStream(iter([(1, "G0 X1")])))
    rig.engine.realtime(Realtime.JOB_KILL)
    await finished(stream)


async def test_alarm_mid_stream_stops_every_action_line_after_it_is_read(rig: Rig) -> None:
    rig.sim.set_ack_delay(0.001)
    stream = rig.job(moves(300, feed=6000))
    await rig.sim.wait_for(lambda: len(rig.received_lines()) > 40)
    rig.sim.limit_switch("y")
    await finished(stream)
    result = stream.result.result()
    assert result.end is StreamEnd.FAILED and result.code == 204
    read_at = rig.recorder.lockout_read_at()
    after = [
        e
        for e in rig.recorder.events[read_at:]
        if isinstance(e, Console) and e.direction == "tx" and e.text.startswith("G")
    ]
    assert after == []
    # Every line written is accounted for: none lost, none re-sent.
    async with asyncio.timeout(2):
        await rig.engine.wait_for(lambda: not len(rig.engine.session.sender))
    assert stream.sent == stream.acked + stream.rejected + stream.discarded
    gcode = [line for line in rig.received_lines() if line.startswith(b"G")]
    assert len(gcode) == len(set(gcode)) or len(gcode) == stream.sent


async def test_interlock_holds_and_resumes_without_a_flush(rig: Rig) -> None:
    stream = rig.job(moves(30, feed=1500))
    await state(rig, S.RUN)
    rig.sim.interlock(True)
    await state(rig, S.INTERLOCK)
    assert not stream.done
    rig.sim.interlock(False)
    await finished(stream)
    assert stream.result.result().end is StreamEnd.COMPLETED
    assert not any(r.data in (b"%", b"\x04") for r in rig.sim.received)


async def test_feedhold_then_flush_cancels_and_frees_the_window(rig: Rig) -> None:
    stream = rig.job(moves(200, feed=600))
    await state(rig, S.RUN)
    rig.engine.realtime(Realtime.FEEDHOLD)
    await state(rig, S.HOLD)
    rig.engine.realtime(Realtime.QUEUE_FLUSH)
    await finished(stream)
    assert stream.result.result().end is StreamEnd.CANCELLED
    await state(rig, S.PROGRAM_STOP)
    assert len(rig.engine.session.sender) == 0
    assert stream.sent == stream.acked + stream.discarded
    assert (await rig.engine.send("G0 X1")).ok  # the window is free again


async def test_job_kill_cancels_and_frees_the_window(rig: Rig) -> None:
    stream = rig.job(moves(200, feed=600))
    await state(rig, S.RUN)
    rig.engine.realtime(Realtime.JOB_KILL)
    await finished(stream)
    assert stream.result.result().end is StreamEnd.CANCELLED
    await state(rig, S.PROGRAM_END)
    async with asyncio.timeout(5):  # the kill's fence, read after it, is answered
        await rig.engine.wait_for(lambda: not rig.engine.session.flushing())
    assert len(rig.engine.session.sender) == 0
    assert (await rig.engine.send("G0 X1")).ok


async def test_in_hold_commands_are_wrapped_in_gc2(rig: Rig) -> None:
    stream = rig.job(moves(100, feed=600))
    await state(rig, S.RUN)
    rig.engine.realtime(Realtime.FEEDHOLD)
    await state(rig, S.HOLD)
    await rig.engine.send("G91 G0 Z5")
    assert b'{"gc2":"G91 G0 Z5"}' in rig.received_lines()
    rig.engine.realtime(Realtime.JOB_KILL)
    await finished(stream)


async def test_a_gcode_error_in_a_job_fails_it_and_kills_the_rest(rig: Rig) -> None:
    stream = rig.job(["G21", "G1 X1 F600", "G5 X2", *moves(20)])
    await finished(stream)
    result = stream.result.result()
    assert result.end is StreamEnd.FAILED and result.code == 1005
    assert result.message is not None and result.message.startswith("line 3:")
    await rig.sim.wait_received(lambda: any(r.data == b"\x04" for r in rig.sim.received))


@pytest.mark.parametrize("good", [1, 11])  # in the first window; read ahead, after writes
async def test_a_job_line_the_board_must_never_get_fails_the_job_unsent(
    rig: Rig, good: int
) -> None:
    stream = rig.job([*moves(good), "G1 X" + "1" * 600, *moves(5)])
    await finished(stream)
    result = stream.result.result()
    assert result.end is StreamEnd.FAILED and result.code == -32602
    assert result.message is not None and result.message.startswith(f"line {good + 1}:")
    assert stream.sent == good  # every line before it went; it and those after it did not


async def test_garbage_from_the_board_does_not_stop_a_job(rig: Rig) -> None:
    stream = rig.job(moves(50))
    for _ in range(5):
        rig.sim.inject_garbage(b"\xff\x00{{{ noise\n")
        await asyncio.sleep(0)
    await finished(stream)
    assert stream.result.result().end is StreamEnd.COMPLETED


async def test_a_read_writes_every_line_its_answers_freed_in_one_write(rig: Rig) -> None:
    """A read is one step: its answers are all taken, then the lines they freed go in
    one write (not the first freed line alone, then the rest: issue 30).

    The board is silent, so the test plays its answers, as one read would
    bring them, into the engine's read callback; the writes go to the real pty.
    """
    rig.sim.go_silent(True)
    link = rig.engine.link
    assert link is not None
    writes: list[tuple[int, list[bytes]]] = []  # (lines acknowledged then, lines written)
    stream = rig.job(moves(20))
    assert stream.sent == 4  # the window, written when the job started

    def spy(lines: list[bytes], *, control: bool = False) -> bool:
        writes.append((stream.acked, list(lines)))
        return Link.write_lines(link, lines, control=control)

    link.write_lines = spy  # type: ignore[method-assign]

    def answers(lines: list[bytes]) -> list[bytes]:
        return [b'{"r":{},"f":[1,0,%d]}' % len(line) for line in lines]

    first = [f"{line}\n".encode() for line in moves(4)]
    rig.engine.link_lines(Channel.DATA, answers(first))
    assert [(acked, len(lines)) for acked, lines in writes] == [(4, 4)]
    written = [line for _, lines in writes for line in lines]
    assert written == [f"{line}\n".encode() for line in moves(8)[4:]]

    writes.clear()  # the board still holds four lines: two answers leave it two
    rig.engine.link_lines(Channel.DATA, answers(written[:2]))
    assert [(acked, len(lines)) for acked, lines in writes] == [(6, 2)]
    assert stream.sent - stream.acked == 4  # the window, never more


# -- the link -----------------------------------------------------------------


async def test_unplug_mid_job_interrupts_it_with_exact_counts(rig: Rig) -> None:
    stream = rig.job(moves(200, feed=600))
    await rig.sim.wait_for(lambda: len(rig.received_lines()) > 20)
    await rig.sim.unplug()
    await finished(stream)
    result = stream.result.result()
    assert result.end is StreamEnd.INTERRUPTED
    assert stream.acked <= stream.sent
    assert rig.engine.link_state is LinkState.DOWN
    await rig.sim.replug()
    await rig.engine.connect()
    assert rig.engine.ready


async def test_a_silent_board_is_declared_lost(tmp_path: Path) -> None:
    path = str(tmp_path / "ttyG2")
    async with SimController(path, config=FAST) as sim:
        recorder = Recorder()
        engine = Engine(machine_config(path, heartbeat=0.2), recorder)
        async with running(engine):
            await engine.connect()
            sim.go_silent(True)
            down = await recorder.wait_for(lambda e: isinstance(e, LinkChanged) and not e.up)
    assert isinstance(down, LinkChanged)
    assert "silent" in down.reason


async def test_a_board_without_banner_fails_to_connect_without_hanging(tmp_path: Path) -> None:
    path = str(tmp_path / "ttyG2")
    async with SimController(path, config=FAST) as sim:
        sim.go_silent(True)
        engine = Engine(machine_config(path, handshake_timeout=0.3))
        async with running(engine):
            with pytest.raises(NotConnected, match="no SYSTEM READY banner"):
                await engine.connect()
            sim.go_silent(False)
            # A later attempt, with a board that talks, works: given the time a handshake
            # takes on a loaded machine (0.3 s is for the banner that never came).
            engine.session.handshake_timeout = 5.0
            await engine.connect()
            assert engine.ready


async def test_a_board_already_in_alarm_connects_and_gets_its_settings_after_clear(
    tmp_path: Path,
) -> None:
    path = str(tmp_path / "ttyG2")
    async with SimController(path, config=FAST) as sim:
        sim.limit_switch("x")
        await sim.wait_state(S.ALARM)
        engine = Engine(machine_config(path))
        async with running(engine):
            await engine.connect()
            assert engine.model.state is S.ALARM
            assert (await engine.send("{jv:n}")).body["jv"] != 4  # refused while alarmed
            await engine.clear()
            async with asyncio.timeout(2):
                await engine.wait_for(lambda: len(engine.session.sender) == 0)
            assert (await engine.send("{jv:n}")).body["jv"] == 4


async def test_tinyg_is_refused_with_a_clear_message(tmp_path: Path) -> None:
    path = str(tmp_path / "ttyG2")
    tinyg = SimConfig(instant=True, fb=440.21)
    async with SimController(path, config=tinyg):
        engine = Engine(machine_config(path))
        async with running(engine):
            with pytest.raises(NotConnected, match="TinyG"):
                await engine.connect()


async def test_dual_port_lines_on_data_realtime_and_queries_on_control(tmp_path: Path) -> None:
    data, ctrl = str(tmp_path / "data"), str(tmp_path / "ctrl")
    async with SimController(data, control_path=ctrl, config=FAST) as sim:
        engine = Engine(machine_config(data, control=ctrl))
        async with running(engine):
            await engine.connect()
            await engine.send("G0 X1")
            await engine.send("{xvm:n}")
            engine.realtime(Realtime.FEEDHOLD)
            await sim.wait_received(lambda: sim.received[-1].data == b"!")
    ports = {r.data: r.port for r in sim.received}
    assert ports[b"G0 X1"] == "data"
    assert ports[b'{"xvm":null}'] == "control"
    assert ports[b"!"] == "control"


async def test_on_two_ports_the_cpu_is_handed_over_after_the_control_ports_bang(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """g2core's `!` goes on the control port, a pty here: the yield follows it there, and
    a line or a query on either port is written without one."""
    data, ctrl = str(tmp_path / "data"), str(tmp_path / "ctrl")
    async with SimController(data, control_path=ctrl, config=FAST) as sim:
        engine = Engine(machine_config(data, control=ctrl))
        async with running(engine):
            await engine.connect()
            yielded: list[None] = []
            monkeypatch.setattr(os, "sched_yield", lambda: yielded.append(None))
            await engine.send("G0 X1")
            await engine.send("{xvm:n}")
            assert yielded == []
            engine.realtime(Realtime.FEEDHOLD)
            assert len(yielded) == 1
            await sim.wait_received(lambda: sim.received[-1].data == b"!")
    assert [r.port for r in sim.received if r.data == b"!"] == ["control"]


async def test_a_uart_board_without_a_banner_is_asked_its_version(tmp_path: Path) -> None:
    path = str(tmp_path / "ttyG2")
    async with SimController(path, config=dataclasses.replace(FAST, uart=True)) as sim:
        engine = Engine(machine_config(path))
        async with running(engine):
            await engine.connect()
            assert engine.ready and engine.model.state is not None
            assert b'{"fv":null,"fb":null}' in [r.data for r in sim.received]
            # After 0x18 the board boots and prints its banner: that is waited for.
            await engine.reset()
            assert engine.ready


@pytest.mark.parametrize(
    ("fb", "refusal"),
    [(440.21, "TinyG firmware \\(build 440.21\\)"), (99.02, "g2core build 99.02 is older")],
)
async def test_firmware_hostd_cannot_drive_is_refused_by_its_version(
    tmp_path: Path, fb: float, refusal: str
) -> None:
    path = str(tmp_path / "ttyG2")
    # Without a banner too: the version answer is enough to tell.
    for uart in (False, True):
        config = SimConfig(instant=True, fb=fb, uart=uart)
        async with SimController(path, config=config):
            engine = Engine(machine_config(path))
            async with running(engine):
                with pytest.raises(NotConnected, match=refusal):
                    await engine.connect()


async def test_a_board_reset_by_its_own_button_gets_the_daemons_settings_again(
    tmp_path: Path,
) -> None:
    path = str(tmp_path / "ttyG2")
    async with SimController(path, config=FAST) as sim:
        engine = Engine(machine_config(path, auto_connect=True))
        async with running(engine):
            await engine.connect()
            applied = sum(r.data == b'{"jv":4}' for r in sim.received)
            await sim.reset()  # the board restarts with its defaults, not the host's doing
            await sim.wait_received(
                lambda: sum(r.data == b'{"jv":4}' for r in sim.received) > applied
            )
            await engine.connect()
            assert (await engine.send("{jv:n}")).body["jv"] == 4


async def test_the_snapshot_shows_what_real_boards_report(rig: Rig) -> None:
    snap = rig.engine.model.snapshot()
    assert snap["homed"] is False  # asked of the board at connect, not guessed
    await rig.engine.send("G55")
    await rig.engine.send("G91 G1 X3 F600")
    await state(rig, S.PROGRAM_STOP)
    await rig.engine.send("{sr:n}")
    snap = rig.engine.model.snapshot()
    assert (snap["wcs"], snap["distance"], snap["feed_mode"], snap["motion"]) == (
        "G55",
        "G91",
        "G94",
        "G1",
    )
    assert snap["machine_position"]["x"] == pytest.approx(3.0)
    assert snap["work_position"] == snap["position"]
    assert snap["tool"] == 0 and snap["hold"] == 0


async def test_homed_is_asked_again_when_a_homing_cycle_ends(rig: Rig) -> None:
    assert rig.engine.model.homed is False
    await rig.engine.send("G28.2 X0 Y0 Z0")
    await rig.engine.wait_for(lambda: rig.engine.model.homed is True)

    def asked() -> int:
        return [r.data for r in rig.sim.received].count(b'{"home":null}')

    await rig.sim.wait_received(lambda: asked() >= 2)  # at connect, and after the cycle


# -- answers that answer no line (issue 12, item 4) --------------------------------


async def test_a_failed_homings_extra_answer_is_booked_to_no_line(rig: Rig) -> None:
    # cycle_homing.cpp `_homing_error_exit` prints {"r":{"msg":..},"f":[1,240,1]}
    # while the line after the G28.2 waits for its answer.
    rig.sim.fail_homing("x", 246)
    rig.sim.set_ack_delay(0.3)
    homing = asyncio.create_task(rig.engine.send("G28.2 X0"))
    asked = asyncio.create_task(rig.engine.send("G0 X1"))
    await rig.sim.wait_received(b"G0 X1")
    assert (await homing).ok
    response = await asked
    assert response.ok  # the real answer reached the line, not the homing report
    report = await rig.recorder.wait_for(lambda e: isinstance(e, ExceptionRaised))
    assert isinstance(report, ExceptionRaised) and report.report["st"] == 240
    assert b'"f":[1,240,1]' in b"".join(s.data for s in rig.sim.sent)
    assert not [e for e in rig.recorder.events if isinstance(e, FaultDetected)]


async def test_startup_messages_are_no_answers(tmp_path: Path) -> None:
    # report.cpp `_startup_helper`: status 15, printed on a UART link at boot.
    path = str(tmp_path / "ttyS")
    async with SimController(path, config=dataclasses.replace(FAST, uart=True)) as sim:
        recorder = Recorder()
        engine = Engine(machine_config(path), recorder)
        async with running(engine):
            await engine.connect()
            await engine.reset()  # it boots, and prints them where the host reads
            assert any(b"Loading configs from EEPROM" in s.data for s in sim.sent)
            assert (await engine.send("{xvm:n}")).body == {"xvm": 6000}
    assert not [e for e in recorder.events if isinstance(e, FaultDetected)]


async def test_a_stop_given_while_an_event_is_told_runs_once_the_step_is_delivered(
    tmp_path: Path,
) -> None:
    """The Machine stops a job from inside the engine's callback (a fault): the call does
    not reach into the session there, it runs once the step's events are handed out,
    in the same delivery, and what it writes goes out then."""
    path = str(tmp_path / "ttyG2")
    async with SimController(path, config=FAST) as sim:
        live_when_asked: list[bool] = []
        engine: Engine

        def on_event(event: object) -> None:
            stream = engine.session.stream
            running = isinstance(event, StatusChanged) and event.report.get("stat") == S.RUN
            if running and stream is not None and not live_when_asked:
                engine.stop_stream(1007, "fault active: lid_open")
                live_when_asked.append(not stream.done)

        engine = Engine(machine_config(path), on_event)
        async with running(engine):
            await engine.connect()
            stream = JobStream(program_lines(moves(200)))
            engine.start_stream(stream)
            async with asyncio.timeout(10):
                result = await stream.result
            # The stop was not run inside the callback: the job was still live there.
            assert live_when_asked == [True]
            assert (result.end, result.code) == (StreamEnd.FAILED, 1007)
            await sim.wait_for(lambda: any(r.data == b"!" for r in sim.received))
