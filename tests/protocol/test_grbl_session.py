"""grbl's session by plain calls: the rules of a one-port, character-counted board.

The board's side is written as grbl prints it (report.c): `ok`, `error:N`,
`ALARM:N`, `<...>` reports, `[...]` feedback. The same rules are tested
against the simulated firmware over ptys in tests/machine/test_grbl.py.
"""

from __future__ import annotations

import math

import pytest

from hostd.protocol.commands import InvalidCommand, Realtime, Refusal
from hostd.protocol.errors import Busy, ControllerError, Rejected
from hostd.protocol.grbl import codec
from hostd.protocol.grbl.connection import BANNER_WAIT
from hostd.protocol.grbl.liveness import STORAGE_QUIET
from hostd.protocol.grbl.overrides import OVERRIDE_HAL_ROUNDS, OVERRIDE_RING, OVERRIDE_ROUNDS
from hostd.protocol.grbl.session import GrblSession
from hostd.protocol.grbl.stops import STOP_TIMEOUT
from hostd.protocol.grbl.words import homing_time_bound
from hostd.protocol.messages import Response
from hostd.protocol.states import MachineState as S
from hostd.protocol.stream import Stream
from hostd.protocol.vocabulary import (
    Closing,
    Event,
    Excepted,
    Lane,
    Probed,
    Ready,
    Settled,
    StreamEnd,
)


class Grbl:
    """A GrblSession and the board's side of the wire, by hand."""

    def __init__(self, **options: float | bool | None) -> None:
        self.now = 0.0
        self.session = GrblSession("m1", clock=lambda: self.now, **options)
        self.written: list[tuple[Lane, bytes]] = []
        self.events: list[Event] = []

    def pump(self) -> list[tuple[Lane, bytes]]:
        out = self.session.data_to_send()
        self.written += out
        self.events += self.session.events()
        return out

    def feed(self, *lines: str) -> list[tuple[Lane, bytes]]:
        for line in lines:
            self.session.receive(line.encode())
        return self.pump()

    def at(self, now: float) -> list[tuple[Lane, bytes]]:
        self.now = now
        self.session.tick()
        return self.pump()

    def lines(self) -> list[bytes]:
        return [data for lane, data in self.written if lane is Lane.DATA]

    def realtime(self) -> list[bytes]:
        return [data for lane, data in self.written if lane is Lane.REALTIME]

    def unanswered_bytes(self) -> int:
        return self.session._rx_used

    def connect(
        self,
        opt: str = "V,15,128",
        report: str = "<Idle|MPos:0.000,0.000,0.000|FS:0,0>",
        settings: tuple[str, ...] = (),
        startup: tuple[str, str] = ("", ""),
        hal: bool = False,
    ) -> None:
        self.session.open()
        if hal:  # grblHAL on native USB: no banner; `$I` says what it is
            self.at(self.now + BANNER_WAIT)
            self.feed(report)  # the `?` asked with `$I`
            self.feed("[VER:1.1f.20240101:]", f"[OPT:{opt}]", "[FIRMWARE:grblHAL]", "ok")
        else:
            self.feed("", "Grbl 1.1h ['$' for help]")
            self.feed(report)  # the `?` asked with `$I`
            self.feed("[VER:1.1h.20190830:]", f"[OPT:{opt}]", "ok")
        self.feed("$32=1", "$110=500.000", "$130=300.000", *settings, "ok")
        self.feed(f"$N0={startup[0]}", f"$N1={startup[1]}", "ok")
        self.feed("[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]", "ok")
        self.feed(report)
        assert self.session.ready
        self.written.clear()
        self.events.clear()

    def settled(self, token: object) -> Settled | None:
        found = [e for e in self.events if isinstance(e, Settled) and e.token is token]
        return found[0] if found else None


IDLE = "<Idle|MPos:0.000,0.000,0.000|FS:0,0>"


def moves(n: int) -> Stream:
    lines = ((i, f"G1 X{i % 100} Y{i % 7} F1000 (step {i}!)") for i in range(1, n + 1))
    return Stream(job_id=1, encode=lambda text, _n: codec.encode(text)).feed_all(lines)


def test_the_handshake_reads_the_build_settings_and_modes_then_a_report() -> None:
    grbl = Grbl()
    grbl.session.open()
    assert grbl.pump() == []  # nothing before the banner (an Arduino is still booting)
    grbl.feed("Grbl 1.1h ['$' for help]")
    assert grbl.lines() == [b"$I\n"]
    assert grbl.realtime() == [b"?"]  # a board busy with moves of before answers only it
    grbl.feed(IDLE)
    grbl.feed("[VER:1.1h.20190830:]", "[OPT:V,15,128]", "ok")
    assert grbl.lines()[-1] == b"$$\n"
    grbl.feed("$32=1", "ok")
    assert grbl.lines()[-1] == b"$N\n"  # the startup blocks: they run at every reset
    grbl.feed("$N0=G54", "$N1=", "ok")
    assert grbl.lines()[-1] == b"$G\n"
    grbl.feed("[GC:G0 G55 G17 G20 G91 G94 M5 M9 T2 F0 S0]", "ok")
    assert grbl.realtime() == [b"?", b"?"]
    assert Ready() not in grbl.events  # the first report came before `$I`'s answer
    grbl.feed("<Idle|WPos:1.000,2.000,0.000|FS:0,0|WCO:10.000,0.000,0.000>")
    assert grbl.events[-1] == Ready()
    model = grbl.session.model
    assert (model.units, model.modal["wcs"], model.modal["distance"], model.tool) == (
        "in",
        "G55",
        "G91",
        2,
    )
    assert model.laser_mode is True
    assert model.position["x"] == 1.0 and model.machine_position["x"] == 11.0


@pytest.mark.parametrize(
    ("modes", "wcs", "motion"),
    [
        # grblHAL 1.1f report.c report_gcode_modes: G50 (scaling off) after G98/G99.
        ("G1 G56 G17 G21 G90 G94 G40 G49 G98 G50 M5 M9 T0 F500 S0", "G56", "G1"),
        ("G0 G54 G92 G17 G21 G90 G94 G40 G43.1 G99 G51:XY M3 M8 T1 F0 S100", "G54", "G0"),
        ("G5.1 G59.2 G18 G21 G91 G93 G40 G49 G98 G50 M5 M9 T0 F0 S0", "G59.2", "G5.1"),
        ("G38.2 G59 G17 G21 G90 G94 M5 M9 T0 F100 S0", "G59", "G38.2"),  # classic 1.1h
    ],
)
def test_the_modes_are_read_by_group_not_by_position(modes: str, wcs: str, motion: str) -> None:
    grbl = Grbl()
    grbl.connect()
    grbl.session.send("$G", object())
    grbl.pump()
    grbl.feed(f"[GC:{modes}]", "ok")
    model = grbl.session.model
    assert (model.modal["wcs"], model.modal["motion"], model.units) == (wcs, motion, "mm")
    assert model.snapshot()["wcs"] == wcs


def test_grblhal_that_prints_no_banner_is_asked_its_build() -> None:
    grbl = Grbl()
    grbl.session.open()
    grbl.at(BANNER_WAIT)
    assert grbl.lines() == [b"$I\n"]
    grbl.feed("[VER:1.1f.20240101:]", "[OPT:VNMSL,100,1024,3,0]", "ok")
    assert (grbl.session.blocks, grbl.session.rx_size) == (100, 1024)


def test_a_board_that_never_answers_closes_the_handshake() -> None:
    grbl = Grbl(handshake_timeout=5.0)
    grbl.session.open()
    grbl.at(5.0)
    (closing,) = [e for e in grbl.events if isinstance(e, Closing)]
    assert "no grbl banner nor answer to $I" in closing.reason


def test_character_counting_never_passes_the_receive_buffer() -> None:
    grbl = Grbl()
    grbl.connect()
    stream = moves(500)
    grbl.session.start_stream(stream)
    worst = 0
    while not stream.done:
        grbl.pump()
        worst = max(worst, grbl.unanswered_bytes())
        if grbl.session._inflight:
            grbl.feed("ok")
        else:
            grbl.feed("<Idle|MPos:0.000,0.000,0.000|Bf:15,128|FS:0,0>")
    assert 100 < worst <= 127  # a ring of 128 holds 127
    assert stream.result.end is StreamEnd.COMPLETED
    assert not any(b"!" in line or b"(" in line for line in grbl.lines())  # comments went


def test_a_job_is_not_done_while_the_planner_still_holds_blocks() -> None:
    grbl = Grbl()
    grbl.connect()
    stream = moves(3)
    grbl.session.start_stream(stream)
    grbl.pump()
    grbl.feed("ok", "ok", "ok")
    grbl.feed("<Idle|MPos:0.000,0.000,0.000|Bf:12,110|FS:0,0>")  # the cycle not started yet
    assert not stream.done
    grbl.feed("<Idle|MPos:2.000,3.000,0.000|Bf:15,128|FS:0,0>")
    assert stream.result.end is StreamEnd.COMPLETED


def test_answers_carry_what_the_board_printed_before_them() -> None:
    grbl = Grbl()
    grbl.connect()
    token = object()
    grbl.session.send("$#", token)
    grbl.pump()
    grbl.feed("[G54:0.000,0.000,0.000]", "[PRB:0.000,0.000,0.000:0]", "ok")
    settled = grbl.settled(token)
    assert settled is not None and isinstance(settled.outcome, Response)
    assert settled.outcome.body["lines"][0] == "[G54:0.000,0.000,0.000]"


def test_a_query_is_a_realtime_byte_answered_by_the_next_report() -> None:
    grbl = Grbl()
    grbl.connect()
    token = object()
    grbl.session.send("?", token)
    assert grbl.pump() == [(Lane.REALTIME, b"?")]
    grbl.feed("<Run|MPos:1.000,0.000,0.000|FS:500,0>")
    settled = grbl.settled(token)
    assert settled is not None and isinstance(settled.outcome, Response)
    assert settled.outcome.body["report"]["state"] == "Run"  # grbl's names: report.c


def test_an_alarm_drains_the_job_and_only_unlock_or_home_get_through() -> None:
    grbl = Grbl()
    grbl.connect()
    stream = moves(50)
    grbl.session.start_stream(stream)
    grbl.pump()
    grbl.feed("ALARM:9")
    assert stream.result.end is StreamEnd.FAILED
    assert stream.result.code == 204
    assert isinstance(grbl.events[-1], Excepted) or any(
        isinstance(e, Excepted) for e in grbl.events
    )
    with pytest.raises(Rejected) as refused:
        grbl.session.send("G0 X1", object())
    assert refused.value.code == 204 and "Could not find limit switch" in refused.value.message
    with pytest.raises(Rejected):
        grbl.session.send("M2", object())  # M2 does not clear a grbl alarm
    grbl.session.send("$H", object())
    grbl.session.send("$$", object())


def test_unlock_waits_for_every_line_to_be_answered() -> None:
    grbl = Grbl()
    grbl.connect()
    grbl.session.send("G0 X1", object())
    grbl.pump()
    grbl.feed("ALARM:2")
    grbl.feed("error:9")  # G0 X1 refused by the alarm
    grbl.feed("<Alarm|MPos:0.000,0.000,0.000|FS:0,0>")
    with pytest.raises(Rejected, match="reads nothing until a reset"):
        grbl.session.clear(object())  # a soft limit is critical: a reset comes first
    grbl.session.reset()
    grbl.pump()
    grbl.feed("", "Grbl 1.1h ['$' for help]", "[MSG:'$H'|'$X' to unlock]", "$N0=", "ok")
    grbl.feed("[GC:G0 G54]", "ok")
    grbl.feed("<Alarm|MPos:0.000,0.000,0.000|FS:0,0>")
    assert grbl.session.ready and grbl.session.model.state is S.ALARM
    token = object()
    assert grbl.session.clear(token)
    grbl.pump()
    assert grbl.lines()[-1] == b"$X\n"


def test_an_estop_is_left_only_by_a_reset() -> None:
    grbl = Grbl()
    grbl.connect()
    grbl.feed("ALARM:10")
    assert grbl.session.model.state is S.SHUTDOWN
    with pytest.raises(Rejected) as refused:
        grbl.session.clear(object())
    assert refused.value.code == 205


def test_no_line_is_run_inside_a_hold() -> None:
    grbl = Grbl()
    grbl.connect()
    grbl.feed("<Hold:0|MPos:0.000,0.000,0.000|FS:0,0>")
    with pytest.raises(Busy, match="grbl runs no line inside"):
        grbl.session.send("M5", object())
    grbl.feed("<Door:1|MPos:0.000,0.000,0.000|FS:0,0>")
    assert grbl.session.model.state is S.INTERLOCK
    with pytest.raises(Busy):
        grbl.session.send("G0 X0", object())


def streaming() -> Grbl:
    """A grbl board running a job of 50 moves, its first line answered."""
    grbl = Grbl()
    grbl.connect()
    grbl.session.start_stream(moves(50))
    grbl.pump()
    grbl.feed("ok", "<Run|MPos:1.000,0.000,0.000|FS:1000,0>")
    return grbl


def test_a_resume_before_the_hold_completes_waits_for_hold_0() -> None:
    """grbl drops a `~` read with its `!` or while the hold decelerates
    (gnea/grbl protocol.c, EXEC_CYCLE_START): the `~` goes once a report says Hold:0."""
    grbl = streaming()
    grbl.session.pause_stream()
    grbl.session.resume_stream()
    grbl.pump()
    assert b"~" not in grbl.realtime() and grbl.realtime()[-2:] == [b"!", b"?"]
    grbl.feed("<Run|MPos:1.100,0.000,0.000|FS:1000,0>")  # read before the `!` took effect
    grbl.feed("<Hold:1|MPos:1.500,0.000,0.000|FS:500,0>")
    assert b"~" not in grbl.realtime()
    grbl.feed("<Hold:0|MPos:1.600,0.000,0.000|FS:0,0>")
    assert grbl.realtime()[-2:] == [b"~", b"?"] and grbl.realtime().count(b"~") == 1
    grbl.feed("<Run|MPos:1.700,0.000,0.000|FS:1000,0>")
    assert grbl.realtime().count(b"~") == 1


def held(lines: int) -> Grbl:
    """A job of `lines` moves paused, its hold reported complete; polls 10 s apart."""
    grbl = Grbl(status_interval=10.0)
    grbl.connect()
    grbl.session.start_stream(moves(lines))
    grbl.pump()
    grbl.feed("<Run|MPos:1.000,0.000,0.000|FS:1000,0>")
    grbl.session.pause_stream()
    grbl.pump()
    grbl.feed("<Hold:0|MPos:1.600,0.000,0.000|FS:0,0>")
    return grbl


def test_a_resumed_job_writes_its_lines_once_a_report_shows_the_hold_left() -> None:
    """grbl reports a `?` read with the `~` before it acts on the `~` (protocol.c
    protocol_exec_rt_system), so the host asks again while reports say Hold; the
    job's lines go as soon as one does not, not at the next poll a `status_interval`
    later, when a laser's planner has long run dry."""
    grbl = held(200)
    for _ in range(4):  # the board's buffer, emptied
        grbl.feed("ok")
    written = len(grbl.lines())
    grbl.session.resume_stream()
    grbl.pump()
    assert grbl.realtime()[-2:] == [b"~", b"?"]
    grbl.feed("<Hold:0|MPos:1.600,0.000,0.000|FS:0,0>")  # read with the `~`: before it
    assert grbl.realtime()[-1] == b"?" and len(grbl.lines()) == written
    grbl.feed("<Run|MPos:1.600,0.000,0.000|FS:1000,0>")
    assert len(grbl.lines()) > written  # at once, with the poll 10 s away
    asks = grbl.realtime().count(b"?")
    grbl.feed("<Run|MPos:1.700,0.000,0.000|FS:1000,0>")
    assert grbl.realtime().count(b"?") == asks  # no more asking once it runs


def test_a_resume_the_board_keeps_holding_is_asked_about_a_bounded_number_of_times() -> None:
    """A `~` the board did not act on (it holds on): three asks, then the usual polls."""
    grbl = held(50)
    asks = grbl.realtime().count(b"?")
    written = len(grbl.lines())
    grbl.session.resume_stream()
    grbl.pump()
    for _ in range(5):
        grbl.feed("<Hold:0|MPos:1.600,0.000,0.000|FS:0,0>")
    assert grbl.realtime().count(b"?") == asks + 3
    assert len(grbl.lines()) == written  # the job's lines wait while the board holds


def test_a_resume_after_the_hold_completed_goes_at_once_and_a_new_hold_voids_a_kept_one() -> None:
    grbl = streaming()
    grbl.session.pause_stream()
    grbl.pump()
    grbl.feed("<Hold:0|MPos:1.600,0.000,0.000|FS:0,0>")
    grbl.session.resume_stream()
    grbl.pump()
    assert grbl.realtime()[-2:] == [b"~", b"?"]  # the hold was complete: no wait
    grbl.feed("<Run|MPos:1.700,0.000,0.000|FS:1000,0>")
    grbl.session.pause_stream()
    grbl.session.resume_stream()
    grbl.session.pause_stream()  # held again before the kept `~` went: it never goes
    grbl.pump()
    grbl.feed("<Hold:0|MPos:1.900,0.000,0.000|FS:0,0>")
    assert grbl.realtime().count(b"~") == 1


def test_a_kept_resume_is_dropped_when_the_board_reports_a_door_instead() -> None:
    grbl = streaming()
    grbl.session.pause_stream()
    grbl.session.resume_stream()
    grbl.pump()
    grbl.feed("<Door:2|MPos:1.500,0.000,0.000|FS:0,0>")  # the door opened meanwhile
    grbl.feed("<Door:0|MPos:1.500,0.000,0.000|FS:0,0>")  # closed: the operator resumes
    assert b"~" not in grbl.realtime()


def test_cancel_holds_then_resets_once_motion_rests() -> None:
    grbl = Grbl()
    grbl.connect()
    stream = moves(50)
    grbl.session.start_stream(stream)
    grbl.pump()
    grbl.feed("ok", "<Run|MPos:1.000,0.000,0.000|FS:1000,0>")
    grbl.session.realtime(Realtime.JOB_KILL)
    grbl.pump()
    assert stream.result.end is StreamEnd.CANCELLED
    assert grbl.realtime()[-2:] == [b"!", b"?"]
    grbl.feed("<Hold:1|MPos:1.500,0.000,0.000|FS:500,0>")
    assert b"\x18" not in grbl.realtime()  # still decelerating: a reset now loses position
    grbl.feed("<Hold:0|MPos:1.600,0.000,0.000|FS:0,0>")
    assert grbl.realtime()[-1] == b"\x18"
    grbl.feed("", "Grbl 1.1h ['$' for help]")
    assert not grbl.session.ready  # re-syncing: $N, $G, then a report
    assert grbl.lines()[-1] == b"$N\n"
    grbl.feed("$N0=", "$N1=", "ok")
    assert grbl.lines()[-1] == b"$G\n"
    grbl.feed(
        "[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]", "ok", "<Idle|MPos:1.600,0.000,0.000|FS:0,0>"
    )
    assert grbl.session.ready and stream.discarded > 0
    assert grbl.session.model.homed is not False  # it had stopped: nothing lost


def test_a_stop_takes_no_report_that_may_predate_its_feedhold_for_rest() -> None:
    """A report printed before the board read the stop's `!` may say Idle while lines it
    holds are about to start a move; a reset then would stop the move dead (ALARM:3,
    position lost). The answer to a `?` already out is such a report; so, on grblHAL,
    is one nobody asked for (its `$481` auto-report). Only a later one says rest."""
    for hal in (False, True):
        grbl = Grbl()
        if hal:
            grbl.connect(opt="VNMHSL,35,1024,3,0", hal=True)
        else:
            grbl.connect()
        stream = moves(50)
        grbl.session.start_stream(stream)
        grbl.pump()
        grbl.feed("ok", "<Idle|MPos:1.000,0.000,0.000|FS:0,0>")  # between two moves
        if not hal:
            grbl.session.query_status()  # a poll, written; its answer still on the wire
            assert grbl.pump()[-1] == (Lane.REALTIME, b"?")
        grbl.session.realtime(Realtime.JOB_KILL)
        grbl.pump()
        assert grbl.realtime()[-2:] == [b"!", b"?"]
        grbl.feed("<Idle|MPos:1.000,0.000,0.000|FS:0,0>")  # printed before the `!`
        assert b"\x18" not in grbl.realtime()
        assert grbl.realtime()[-1] == b"?"  # asked again
        grbl.feed("<Hold:0|MPos:1.000,0.000,0.000|FS:0,0>")
        assert grbl.realtime()[-1] == b"\x18"


def test_a_stop_that_never_rests_resets_anyway_and_says_position_unknown() -> None:
    grbl = Grbl()
    grbl.connect()
    grbl.session.model.homed = True
    grbl.feed("<Run|MPos:1.000,0.000,0.000|FS:1000,0>")
    grbl.session.realtime(Realtime.QUEUE_FLUSH)
    grbl.pump()
    written = grbl.at(STOP_TIMEOUT)
    assert (Lane.REALTIME, b"\x18") in written  # a `?` unanswered since may be asked again
    assert grbl.session.model.homed is False


def test_a_jog_is_stopped_with_jog_cancel() -> None:
    grbl = Grbl()
    grbl.connect()
    assert grbl.session.jog_lines({"x": 1.5}, 600) == ["$J=G91 X1.5000 F600.000"]
    grbl.feed("<Jog|MPos:1.000,0.000,0.000|FS:600,0>")
    grbl.session.realtime(Realtime.QUEUE_FLUSH)
    assert grbl.pump() == [(Lane.REALTIME, b"\x85")]


def test_a_probe_result_is_kept_and_told() -> None:
    grbl = Grbl()
    grbl.connect()
    grbl.feed("[PRB:1.000,2.000,-3.250:1]")
    (probe,) = [e for e in grbl.events if isinstance(e, Probed)]
    assert probe.probe == {"ok": True, "position": {"x": 1.0, "y": 2.0, "z": -3.25}}


def test_a_job_line_error_fails_the_job_and_stops_the_board() -> None:
    grbl = Grbl()
    grbl.connect()
    stream = moves(10)
    grbl.session.start_stream(stream)
    grbl.pump()
    grbl.feed("<Run|MPos:1.000,0.000,0.000|FS:1000,0>", "ok", "error:20")
    result = stream.result
    assert result.end is StreamEnd.FAILED and "line 2" in (result.message or "")
    assert "error:20" in (result.message or "")
    assert grbl.realtime()[-2:] == [b"!", b"?"]  # the lines behind it would run: stop


def test_after_a_job_line_error_the_session_is_not_quiet_until_the_reset_is_over() -> None:
    """The failed job's stop (a hold, then 0x18) would throw away a client's line sent
    meanwhile: until the board is back, the machine is not at rest (Machine._settle)."""
    grbl = Grbl()
    grbl.connect()
    stream = moves(2)
    grbl.session.start_stream(stream)
    grbl.pump()
    grbl.feed("ok", "error:20")
    assert stream.done and grbl.session.no_data_in_flight()
    assert not grbl.session.quiet()  # stopping: `!` went, the board is not at rest yet
    grbl.feed("<Hold:0|MPos:1.000,0.000,0.000|FS:0,0>")
    assert grbl.realtime()[-1] == codec.RESET
    assert not grbl.session.quiet()  # resetting
    grbl.feed("Grbl 1.1h ['$' for help]")  # the reset's welcome: it re-syncs
    grbl.feed("$N0=", "$N1=", "ok")
    grbl.feed("[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]", "ok")
    grbl.feed(IDLE)
    assert grbl.session.ready and grbl.session.quiet()


def test_what_reports_said_now_and_then_is_forgotten_with_the_connection() -> None:
    """`WCO:` comes only in some reports, `Bf:` in each while `$10` asks for it: a planner
    full before an unplug must not keep a job on the next connection, whose board
    prints no Bf, from ever being at rest, hence done; nor the old offset stay."""
    grbl = Grbl()
    grbl.connect(report="<Run|MPos:1.000,0.000,0.000|Bf:0,128|FS:1000,0|WCO:5.000,0.000,0.000>")
    grbl.session.close("unplugged")
    grbl.connect()  # this board's reports carry no Bf
    model = grbl.session.model
    assert model.machine_position["x"] == 0.0
    assert "x" not in model.position  # not the last connection's offset: not known yet
    stream = moves(1)
    grbl.session.start_stream(stream)
    grbl.pump()
    grbl.feed("ok")
    grbl.feed(IDLE)
    assert stream.done and stream.result.end is StreamEnd.COMPLETED


def test_a_report_without_bf_says_nothing_of_the_planner() -> None:
    """`$10` changed to leave Bf out: the last Bf read no longer holds a job back."""
    grbl = Grbl()
    grbl.connect(report="<Idle|MPos:0.000,0.000,0.000|Bf:0,128|FS:0,0>")
    stream = moves(1)
    grbl.session.start_stream(stream)
    grbl.pump()
    grbl.feed("ok")
    grbl.feed(IDLE)  # no Bf: the planner is not known to hold anything
    assert stream.done and stream.result.end is StreamEnd.COMPLETED


@pytest.mark.parametrize(
    ("line", "why"),
    [
        ("G0 X1 !", "realtime"),
        ("G0 X1 ~", "realtime"),
        ("G0 X\u00e91", "not-text"),
        ("G0 " + "X1 " * 60, "too-long"),
    ],
)
def test_lines_grbl_would_misread_are_refused(line: str, why: str) -> None:
    grbl = Grbl()
    grbl.connect()
    with pytest.raises(InvalidCommand) as refused:
        grbl.session.send(line, object())
    assert refused.value.data["refusal"] == why


def closings(grbl: Grbl) -> list[Closing]:
    return [e for e in grbl.events if isinstance(e, Closing)]


def queries(grbl: Grbl) -> int:
    return grbl.realtime().count(b"?")


# grbl 1.1's defaults.h (DEFAULTS_GENERIC) for homing: feed 25, seek 500 mm/min, 250 ms
# debounce, 1 mm pull-off, 200 mm of travel and 10 mm/s^2 on each axis.
HOMING_SETTINGS = (
    "$24=25.000",
    "$25=500.000",
    "$26=250",
    "$27=1.000",
    *(f"$12{i}=10.000" for i in range(3)),
    *(f"$13{i}=200.000" for i in range(3)),
)


def homing_board(**options: float) -> Grbl:
    grbl = Grbl(heartbeat=2.0, status_interval=0.25, link_silence=10.0, **options)
    grbl.connect(settings=HOMING_SETTINGS)
    return grbl


def test_a_silent_board_is_asked_again_and_given_up_only_after_the_configured_silence() -> None:
    grbl = Grbl(heartbeat=2.0, status_interval=0.25, link_silence=10.0)
    grbl.connect()
    grbl.at(0.25)
    assert queries(grbl) == 1
    grbl.at(2.25)
    grbl.at(4.25)
    assert queries(grbl) == 3  # a `?` unanswered for `heartbeat` is asked again
    grbl.at(9.9)
    assert closings(grbl) == []
    assert grbl.session.next_deadline() == 10.0
    grbl.at(10.0)
    (closing,) = closings(grbl)
    assert "silent for 10.0 s" in closing.reason and "3 status requests" in closing.reason
    assert closing.reopen  # it stood idle: reopening its port harms nothing


def test_a_single_lost_query_is_asked_again_and_the_job_goes_on() -> None:
    grbl = Grbl(heartbeat=2.0, status_interval=0.25, link_silence=10.0)
    grbl.connect()
    stream = moves(40)
    grbl.session.start_stream(stream)
    grbl.pump()
    grbl.at(0.25)  # this `?` is lost on the wire: no report comes
    grbl.at(1.0)
    assert queries(grbl) == 1  # not asked again before `heartbeat`
    grbl.at(2.25)
    assert queries(grbl) == 2
    grbl.feed("<Run|MPos:1.000,0.000,0.000|Bf:10,20|FS:1000,0>")
    grbl.at(2.5)
    assert queries(grbl) == 3  # back to every status_interval
    assert closings(grbl) == [] and not stream.done


def test_oks_keep_a_board_alive_while_its_status_reports_stop() -> None:
    grbl = Grbl(heartbeat=2.0, status_interval=0.25, link_silence=10.0)
    grbl.connect()
    stream = moves(400)
    grbl.session.start_stream(stream)
    grbl.pump()
    sent = len(grbl.lines())
    for tick in range(1, 61):  # half a minute of `ok`s, twice a second, and not one report
        grbl.at(tick / 2)
        grbl.feed("ok")
    assert closings(grbl) == []
    assert not stream.done
    assert len(grbl.lines()) >= sent + 55  # the `ok`s freed room: lines kept going
    assert 14 <= queries(grbl) <= 16  # `?` asked again every `heartbeat`, never given up on


def test_a_board_silent_mid_job_is_given_up_but_its_port_not_reopened() -> None:
    grbl = Grbl(heartbeat=2.0, status_interval=0.25, link_silence=10.0)
    grbl.connect()
    stream = moves(40)
    grbl.session.start_stream(stream)
    grbl.pump()
    grbl.feed("ok", "<Run|MPos:1.000,0.000,0.000|Bf:10,20|FS:1000,0>")
    for t in range(1, 11):
        grbl.at(float(t))
    grbl.at(12.0)
    (closing,) = closings(grbl)
    assert not closing.reopen and "may be moving" in closing.reason
    grbl.session.close(closing.reason)
    assert stream.result.end is StreamEnd.INTERRUPTED


def test_classic_homing_is_silent_for_its_whole_cycle_and_completes() -> None:
    grbl = homing_board()
    token = object()
    grbl.session.send("$H", token)
    assert grbl.pump() == [(Lane.DATA, b"$H\n")]
    # limits_go_home serves no `?` (limits.c): not a byte for two and a half minutes.
    for t in range(1, 151):
        grbl.at(float(t))
    assert closings(grbl) == []
    assert queries(grbl) >= 70  # still asked, as the board takes no harm from it
    grbl.feed("ok", "<Idle|MPos:-1.000,-1.000,-1.000|FS:0,0>")
    settled = grbl.settled(token)
    assert settled is not None and settled.outcome == Response({}, 0, 0, b"ok")
    assert grbl.session.model.homed is True
    grbl.at(151.0)
    grbl.at(160.0)
    assert closings(grbl) == []


def test_a_homing_cycle_is_bounded_by_the_boards_travel_and_feeds() -> None:
    grbl = homing_board()
    bound = homing_time_bound(grbl.session.settings)
    # Per axis: 300 mm at 500 mm/min, 2 pull-offs of 1 mm at 500, 10 mm at 25 mm/min,
    # 4 debounces of 0.25 s and 4 accelerations; three axes, and half as much again.
    per_axis = 36.0 + 2 * 0.12 + 24.0 + 1.0 + 3 * (500 / 60 / 10) + 25 / 60 / 10
    assert bound == pytest.approx(1.5 * 3 * per_axis, rel=1e-3)
    grbl.session.send("$H", object())
    grbl.pump()
    t = 0.0
    while not closings(grbl) and t < 1000:
        t += 1.0
        grbl.at(t)
    (closing,) = closings(grbl)
    assert t == pytest.approx(bound, abs=1.0)  # a board gone mid-cycle is still found
    assert not closing.reopen  # it may be moving: an Arduino's reset would stop it there


def test_a_configured_homing_timeout_replaces_the_bound() -> None:
    grbl = homing_board(homing_timeout=60.0)
    grbl.session.send("$H", object())
    grbl.pump()
    for t in range(1, 60):
        grbl.at(float(t))
    assert closings(grbl) == []
    grbl.at(60.0)
    assert len(closings(grbl)) == 1


def test_homing_without_the_settings_to_bound_it_is_never_cut_off() -> None:
    grbl = Grbl(heartbeat=2.0, status_interval=0.25, link_silence=10.0)
    grbl.connect()  # `$$` said nothing of $24/$25/$130
    grbl.session.send("$H", object())
    grbl.pump()
    for t in range(1, 3601, 60):
        grbl.at(float(t))
    assert closings(grbl) == []


def test_grblhal_reporting_home_expects_the_silence_of_a_cycle() -> None:
    grbl = Grbl(heartbeat=2.0, status_interval=0.25, link_silence=10.0)
    grbl.connect(settings=HOMING_SETTINGS)
    # A cycle started on the board (a button, `$H` from another sender): its one report.
    grbl.feed("<Home|MPos:0.000,0.000,0.000|FS:0,0>")
    for t in range(1, 201):
        grbl.at(float(t))
    assert closings(grbl) == []
    grbl.feed("<Idle|MPos:-1.000,-1.000,-1.000|FS:0,0>")
    for t in range(201, 213):
        grbl.at(float(t))
    assert len(closings(grbl)) == 1  # homing over: the usual silence again


def test_a_failed_homing_answered_ok_by_classic_grbl_does_not_say_homed() -> None:
    grbl = homing_board()
    grbl.session.send("$H", object())
    grbl.pump()
    # grbl 1.1h system.c: the cycle fails (limits.c raises the alarm), `$H` still says ok.
    grbl.feed("ALARM:8", "ok")
    assert grbl.session.model.homed is False
    grbl.feed("<Alarm|MPos:0.000,0.000,0.000|FS:0,0>")
    assert grbl.session.model.state is S.ALARM
    grbl.session.send("$H", object())
    grbl.pump()
    grbl.feed("ok")  # the next cycle succeeds
    assert grbl.session.model.homed is True


def test_a_failed_homing_grblhal_resets_after_says_the_alarm_not_a_status() -> None:
    """grblHAL answers no `$H` whose cycle failed: it prints the alarm, then resets itself
    (its banner again). The `$H` is settled with the alarm that caused the reset, status
    0 (grbl has no code for it: its error:3 is an unknown `$` command), never as an
    answer the board did not give."""
    grbl = homing_board()
    home, move = object(), object()
    grbl.session.send("$H", home)
    grbl.session.send("G0 X1", move)
    grbl.pump()
    grbl.feed("ALARM:9", "", "GrblHAL 1.1f ['$' or '$HELP' for help]")
    for token in (home, move):
        settled = grbl.settled(token)
        assert settled is not None and isinstance(settled.outcome, ControllerError)
        error = settled.outcome
        assert error.status == 0 and error.data == {"status": 0, "msg": error.args[0]}
        assert error.args[0] == (
            "not answered: the controller reset itself after ALARM:9 (Homing fail. "
            "Could not find limit switch within search distances.)"
        )
    assert grbl.session.model.homed is False


def test_a_job_the_board_reset_under_says_whether_it_was_ours_and_the_alarm() -> None:
    """A board that resets itself mid-job with no alarm before (a brown-out, a watchdog)
    fails the job saying so; not "the controller was reset", which the host's own reset
    is. (After an alarm the alarm has ended the job already, with its code.)"""
    grbl = Grbl()
    grbl.connect()
    stream = moves(50)
    grbl.session.start_stream(stream)
    grbl.pump()
    grbl.feed("", "Grbl 1.1h ['$' for help]")  # a power glitch: no alarm before
    assert stream.result is not None and stream.result.end is StreamEnd.FAILED
    assert stream.result.message == "the controller reset itself"


def test_a_reset_with_no_alarm_before_it_says_only_that() -> None:
    """An alarm answered since (a `$X`'s ok) is not the cause of a later reset."""
    grbl = homing_board()
    grbl.feed("ALARM:9")
    grbl.session.send("$X", object())
    grbl.pump()
    grbl.feed("ok")
    line = object()
    grbl.session.send("$$", line)
    grbl.pump()
    grbl.feed("", "Grbl 1.1h ['$' for help]")
    settled = grbl.settled(line)
    assert settled is not None and isinstance(settled.outcome, ControllerError)
    assert str(settled.outcome.args[0]) == "not answered: the controller reset itself"


def test_the_spindle_is_read_from_any_report_that_says_a_and_from_ov_without_it() -> None:
    """grblHAL says `A:` alone on the report after a change, `A:` empty when all went off;
    classic grbl only beside `Ov:`, leaving A out when none is on. A report with neither
    says nothing of the spindle."""
    grbl = Grbl()
    grbl.connect()
    for tail, state, speed in (
        ("FS:0,500|A:S", "cw", 500),  # grblHAL: A alone, on the report after M3
        ("FS:0,500", "cw", 500),  # neither: unchanged
        ("FS:0,500|A:CF", "ccw", 500),
        ("FS:0,0|A:", "off", 0),  # grblHAL: all off
        ("FS:0,300|Ov:100,100,100|A:S", "cw", 300),
        ("FS:0,0|Ov:100,100,100", "off", 0),  # classic: Ov without A
    ):
        grbl.feed(f"<Idle|MPos:0.000,0.000,0.000|{tail}>")
        assert grbl.session.model.spindle == {"state": state, "speed": speed}, tail


@pytest.mark.parametrize(("hal", "held"), [(False, "1"), (True, "9")])
def test_a_setting_written_is_what_the_session_holds_without_a_new_read(
    hal: bool, held: str
) -> None:
    """`$22=9` answered ok: classic grbl keeps a flag (`$$` would say 1), grblHAL the
    number; `$32=1` is laser mode at once. A write the board refused changes nothing."""
    grbl = Grbl()
    grbl.connect(hal=hal)
    for line in ("$22=9", "$32=1", "$13=1"):
        grbl.session.send(line, object())
        grbl.pump()
        grbl.feed("ok")
    assert grbl.session.settings["22"] == held
    assert grbl.session.model.laser_mode is True
    assert grbl.session.position_scales() == (25.4, 25.4)  # `$13=1`: reports in inches
    grbl.session.send("$13=0", object())
    grbl.pump()
    grbl.feed("error:3")
    assert grbl.session.position_scales() == (25.4, 25.4)


def test_a_clients_gcode_line_is_followed_by_a_modes_read_and_a_job_end_too() -> None:
    """grbl says its modes only in `$G`: after a client's `G20` the session asks, and its
    units are the board's from the answer (a jog's bound is checked in them). A `$` line
    asks nothing; a completed job asks once."""
    grbl = Grbl()
    grbl.connect()
    grbl.session.send("G20", object())
    grbl.pump()
    grbl.feed("ok")
    assert grbl.lines()[-1] == b"$G\n"
    grbl.feed("[GC:G0 G54 G17 G20 G90 G94 M5 M9 T0 F0 S0]", "ok")
    assert grbl.session.model.units == "in"
    grbl.session.send("$#", object())
    grbl.pump()
    grbl.feed("ok")
    assert grbl.lines()[-1] == b"$#\n"  # no read after a `$` line
    stream = moves(3)
    grbl.session.start_stream(stream)
    grbl.pump()
    grbl.feed("ok", "ok", "ok", IDLE)
    assert stream.result is not None and stream.result.end is StreamEnd.COMPLETED
    grbl.pump()
    assert grbl.lines()[-1] == b"$G\n"


def test_help_is_not_homing() -> None:
    grbl = Grbl()
    grbl.connect()
    grbl.session.send("$HELP", object())
    grbl.pump()
    grbl.feed("[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]", "ok")
    assert grbl.session.model.homed is not True


def test_settings_are_written_send_response_as_the_board_may_be_deaf_meanwhile() -> None:
    grbl = Grbl(heartbeat=2.0, status_interval=0.25, link_silence=10.0)
    grbl.connect()
    first, second, query = object(), object(), object()
    grbl.session.send("$110=600", first)
    grbl.session.send("$111=600", second)
    grbl.session.send("$$", query)
    assert grbl.pump() == [(Lane.DATA, b"$110=600\n")]  # nothing after it until its `ok`
    for t in range(1, 12):  # the write keeps it quiet for longer than `link_silence`
        grbl.at(float(t))
    assert closings(grbl) == []
    grbl.feed("ok")
    assert grbl.lines()[-1] == b"$111=600\n"
    grbl.feed("ok")
    assert grbl.lines()[-1] == b"$$\n"
    grbl.feed("$110=600.000", "ok")
    assert closings(grbl) == []


def test_grblhal_may_be_quiet_after_answering_a_setting_while_it_writes_flash() -> None:
    grbl = Grbl(heartbeat=2.0, status_interval=0.25, link_silence=10.0)
    grbl.connect()
    grbl.session.send("$110=600", object())
    grbl.pump()
    grbl.feed("ok")  # grblHAL answers first, then writes its flash once idle
    for t in range(1, 12):
        grbl.at(float(t))
    assert closings(grbl) == []
    grbl.at(10.0 + STORAGE_QUIET)
    assert len(closings(grbl)) == 1


def test_a_job_line_that_stores_offsets_is_answered_before_the_next_is_written() -> None:
    grbl = Grbl()
    grbl.connect()
    text = ["G1 X1 F100", "G10 L20 P1 X0", "G1 X2", "G28.1", "G1 X3"]
    stream = Stream(job_id=1, encode=lambda line, _n: codec.encode(line)).feed_all(
        enumerate(text, 1)
    )
    grbl.session.start_stream(stream)
    assert [data for _, data in grbl.pump()] == [b"G1 X1 F100\n", b"G10 L20 P1 X0\n"]
    grbl.feed("ok")
    assert grbl.pump() == []
    grbl.feed("ok")
    assert grbl.lines()[-2:] == [b"G1 X2\n", b"G28.1\n"]
    grbl.feed("ok", "ok")
    assert grbl.lines()[-1] == b"G1 X3\n"


def test_the_homing_bound_needs_the_feeds_and_a_travel() -> None:
    assert homing_time_bound({}) is None
    assert homing_time_bound({"24": "25", "25": "500"}) is None  # no travel
    assert homing_time_bound({"25": "500", "130": "200"}) is None  # no locate feed
    one = homing_time_bound({"24": "25", "25": "500", "130": "200", "27": "1"})
    two = homing_time_bound({"24": "25", "25": "500", "130": "200", "27": "1", "43": "2"})
    assert one is not None and two is not None and two > one  # grblHAL's $43 locate cycles
    # What a board prints is not trusted: no overflow, no endless list, no NaN.
    for odd in ({"43": "1e300"}, {"43": "nan"}, {"130": "inf"}, {"25": "nan"}):
        bound = homing_time_bound({"24": "25", "25": "500", "130": "200", "27": "1"} | odd)
        assert bound is None or math.isfinite(bound)


def ov(values: str, extra: str = "") -> str:
    """A report with `Ov:` (feed, rapid, spindle), as one after an override change."""
    return f"<Idle|MPos:0.000,0.000,0.000|FS:0,0{extra}|Ov:{values}>"


def rt(*data: bytes) -> list[tuple[Lane, bytes]]:
    return [(Lane.REALTIME, b) for b in data]


def test_a_classic_override_round_is_one_byte_of_a_kind_then_steps_from_the_report() -> None:
    """Classic grbl applies one flag bit per kind a pass (gnea/grbl protocol.c:405-452):
    a round writes a reset, one step of ten and one of one; the next rounds step from
    what a report said, until it says what was asked."""
    grbl = Grbl()
    grbl.connect()
    grbl.session.override(feed=112, rapid=25, spindle=98)
    assert grbl.pump() == rt(b"\x97", b"\x90", b"\x91", b"\x93", b"\x99", b"\x9d", b"?")
    # Its report may have been read in the bytes' pass, answered before they acted.
    assert grbl.feed(ov("100,100,100")) == rt(b"?")
    assert grbl.session.override_answers == 0
    # Asked after that one arrived: it postdates them. The next round starts from it.
    assert grbl.feed(ov("111,25,99")) == rt(b"\x93", b"\x9d", b"?")
    assert grbl.feed(ov("111,25,99")) == rt(b"?")
    assert grbl.session.override_answers == 0
    assert grbl.feed(ov("112,25,98")) == []
    assert grbl.session.override_answers == 1
    assert grbl.session.model.overrides == {"feed": 112, "rapid": 25, "spindle": 98}
    assert grbl.feed(ov("112,25,98")) == [] and grbl.session.override_answers == 1
    # Only the values asked are compared: rapid was not, and stays the board's.
    grbl.session.override(spindle=99)
    assert grbl.pump() == rt(b"\x99", b"\x9d", b"?")
    assert grbl.feed(ov("112,25,98")) == rt(b"?")
    assert grbl.feed(ov("112,25,99")) == [] and grbl.session.override_answers == 2


def test_an_override_is_not_answered_by_a_report_that_may_predate_its_bytes() -> None:
    """The board already at 150: the report read with the bytes says 150, but the reset
    and "+10" then act (110). The answer waits for a report asked after it."""
    grbl = Grbl()
    grbl.connect(report=ov("150,100,100"))
    grbl.session.override(feed=150)
    assert grbl.pump() == rt(b"\x90", b"\x91", b"?")
    assert grbl.feed(ov("150,100,100")) == rt(b"?")
    assert grbl.session.override_answers == 0
    assert grbl.feed(ov("110,100,100")) == rt(b"\x91", b"?")
    for feed in (120, 130, 140):
        assert grbl.feed(ov(f"{feed - 10},100,100")) == rt(b"?")
        assert grbl.feed(ov(f"{feed},100,100")) == rt(b"\x91", b"?")
    assert grbl.feed(ov("140,100,100")) == rt(b"?")
    assert grbl.feed(ov("150,100,100")) == []
    assert grbl.session.override_answers == 1


def test_an_override_written_while_a_request_is_out_reads_one_report_more() -> None:
    """A `?` unanswered when the bytes go may be answered first, before they arrive:
    then the report read with them, then one that surely follows them."""
    grbl = Grbl()
    grbl.connect(report=ov("150,100,100"))
    grbl.session.send("?", "client")
    assert grbl.pump() == rt(b"?")
    grbl.session.override(feed=150)
    assert grbl.pump() == rt(b"\x90", b"\x91", b"?")
    assert grbl.feed(ov("150,100,100")) == rt(b"?")  # the client's
    assert grbl.feed(ov("150,100,100")) == rt(b"?")  # read with the bytes
    assert grbl.session.override_answers == 0
    assert grbl.feed(ov("110,100,100")) == rt(b"\x91", b"?")


def hal_grbl() -> Grbl:
    grbl = Grbl()
    grbl.connect(opt="VNMHSL,35,1024,3,0", hal=True)
    assert grbl.session.flavour == "GrblHAL"  # from `$I`, no banner
    return grbl


FEED_RESET, FEED_UP_10, FEED_UP_1, FEED_DOWN_1 = b"\x90", b"\x91", b"\x93", b"\x94"
SPINDLE_RESET, SPINDLE_DOWN_10, SPINDLE_UP_1 = b"\x99", b"\x9b", b"\x9c"


def test_a_grblhal_override_round_is_a_reset_and_the_fewest_steps_its_rings_hold() -> None:
    """grblHAL queues override bytes in rings of 15 (override.c:35-43), feed and rapid in
    one (protocol.c:941-950), and drops what does not fit. A round is a reset, then the
    fewest steps, never leaving 10..200: 100 to 199 is ten tens and one down (12
    bytes), not nine and nine (19)."""
    grbl = hal_grbl()
    grbl.session.override(feed=199, rapid=25, spindle=11)
    motion = [b"\x97", FEED_RESET, *[FEED_UP_10] * 10, FEED_DOWN_1]
    accessory = [SPINDLE_RESET, *[SPINDLE_DOWN_10] * 9, SPINDLE_UP_1]
    assert grbl.pump() == rt(*motion, *accessory, b"?")
    # Three reports: one nobody asked for, the one read with the bytes, then one after.
    assert grbl.feed(ov("100,100,100")) == rt(b"?")
    assert grbl.feed(ov("100,100,100")) == rt(b"?")
    assert grbl.feed(ov("199,25,11")) == []
    assert grbl.session.override_answers == 1
    assert grbl.session.model.overrides == {"feed": 199, "rapid": 25, "spindle": 11}


@pytest.mark.parametrize("what", ["feed", "spindle"])
def test_a_round_from_a_reset_sets_any_value_from_any_within_one_ring(what: str) -> None:
    """`override_from_reset`, applied as grblHAL applies each byte (clamped to 10..200,
    protocol.c:631-722): every value from every value, in at most 15 bytes (one ring),
    no step clamped (the board would lose the count), the same bytes again change
    nothing, and no step passes the value unless the steps that do not would overfill
    the ring (then within the pass that drains it)."""
    low, high = codec.OVERRIDE_RANGE
    names = {byte: name for name, byte in codec.OVERRIDES.items()}

    def apply(value: int, data: list[bytes]) -> int:
        for byte in data:
            name = names[byte]
            if name.endswith("_reset"):
                value = 100
                continue
            step = int(name.rsplit("_", 1)[1]) * (1 if "_plus_" in name else -1)
            assert low <= value + step <= high, (name, value)
            value += step
        return value

    def passes(data: list[bytes], target: int) -> int:
        """How far past `target` (seen from 100) the steps go on their way."""
        value, past = 100, 0
        for byte in data[1:]:
            value = apply(value, [byte])
            if (value - target) * (100 - target) < 0:
                past = max(past, abs(value - target))
        return past

    passing = []
    for target in range(low, high + 1):
        data = codec.override_from_reset(target, what, OVERRIDE_RING)
        assert len(data) <= OVERRIDE_RING
        for start in (low, 100, target, high):
            assert apply(apply(start, data), data) == target
        if past := passes(data, target):
            passing.append(target)
            assert past <= 4  # the multiple of ten nearest beyond it (196 by 200)
            # Only where the steps that never pass it would not fit the ring.
            tens, ones = divmod(abs(target - 100), 10)
            assert 1 + tens + ones > OVERRIDE_RING
    assert len(codec.override_from_reset(195, what, OVERRIDE_RING)) == OVERRIDE_RING
    assert 199 in passing and 11 in passing and 173 not in passing and 57 not in passing


def test_a_grblhal_round_over_its_ring_is_cut_and_the_rest_goes_from_a_reset() -> None:
    """Rapid and 100 to 195 (a reset, nine tens, five ones) are 16 bytes for the ring of
    15: the round writes 15; the next, rapid in force, the feed alone from a reset."""
    grbl = hal_grbl()
    grbl.session.override(feed=195, rapid=50)
    feed = [FEED_RESET, *[FEED_UP_10] * 9, *[FEED_UP_1] * 5]
    assert grbl.pump() == rt(b"\x96", *feed[:14], b"?")
    assert grbl.feed(ov("100,100,100")) == rt(b"?")
    assert grbl.feed(ov("100,100,100")) == rt(b"?")
    assert grbl.feed(ov("194,50,100")) == rt(*feed, b"?")
    for _ in range(2):
        assert grbl.feed(ov("194,50,100")) == rt(b"?")
    assert grbl.feed(ov("195,50,100")) == []
    assert grbl.session.model.overrides == {"feed": 195, "rapid": 50, "spindle": 100}


def test_a_grblhal_override_read_too_early_is_written_again_never_stepped_past() -> None:
    """grblHAL prints reports nobody asked for (its `$481` auto-report, grbllib.c:160-167;
    one as a homing cycle starts or a tool change ends): one may come between the host's
    bytes and the pass that reads them, and the report to the round's `?` may be read
    in that pass, before they act. Against the upstream Simulator with `$481=200`,
    stepping on from such a report took an override asked at 173 to 200. A round is
    written from a reset again, never stepped from a report that may be old."""
    grbl = hal_grbl()
    grbl.session.override(feed=173, spindle=57)
    first = grbl.pump()
    assert first == rt(
        FEED_RESET, *[FEED_UP_10] * 7, *[FEED_UP_1] * 3,
        SPINDLE_RESET, *[SPINDLE_DOWN_10] * 4, *[b"\x9d"] * 3, b"?",
    )  # fmt: skip
    # An auto-report, then the one read with the bytes: both before the bytes act.
    assert grbl.feed(ov("100,100,100")) == rt(b"?")
    assert grbl.feed(ov("100,100,100")) == rt(b"?")
    # Later still, the board had not read them (a slow reader, as the Simulator is):
    # the next round is the same bytes, from a reset, not steps from this 100.
    assert grbl.feed(ov("100,100,100")) == first
    for _ in range(2):
        assert grbl.feed(ov("173,100,57")) == rt(b"?")
    assert grbl.feed(ov("173,100,57")) == []
    assert grbl.session.override_answers == 1
    assert grbl.session.model.overrides == {"feed": 173, "rapid": 100, "spindle": 57}


def test_a_grblhal_board_that_keeps_other_values_is_answered_after_its_rounds() -> None:
    """A build with other bounds (MAX_FEED_RATE_OVERRIDE 120, grbl.h) clamps every round:
    after OVERRIDE_HAL_ROUNDS, the answer is what it said, with a warning."""
    grbl = hal_grbl()
    grbl.session.override(feed=150)
    round_ = [FEED_RESET, *[FEED_UP_10] * 5, b"?"]
    assert grbl.pump() == rt(*round_)
    for n in range(1, OVERRIDE_HAL_ROUNDS + 1):
        assert grbl.feed(ov("120,100,100")) == rt(b"?")
        assert grbl.feed(ov("120,100,100")) == rt(b"?")
        out = grbl.feed(ov("120,100,100"))
        assert out == (rt(*round_) if n < OVERRIDE_HAL_ROUNDS else [])
    assert grbl.session.override_answers == 1
    assert grbl.session.model.overrides == {"feed": 120, "rapid": 100, "spindle": 100}


def test_an_override_the_board_stops_moving_towards_is_answered_as_it_says() -> None:
    """A board that keeps other values (a grblHAL built with MAX_FEED_RATE_OVERRIDE 120
    clamps there, grbl.h): once a round brings nothing nearer, the answer is its 120.
    A report with no `Ov:` says no value changed (report.c:615-619), unless it shows
    WCO: classic grbl then puts `Ov:` in the next one (report.c:608)."""
    grbl = Grbl()
    grbl.connect()
    grbl.session.override(feed=150)
    grbl.pump()
    assert grbl.feed(ov("100,100,100")) == rt(b"?")
    assert grbl.feed(ov("110,100,100")) == rt(b"\x91", b"?")
    assert grbl.feed(ov("110,100,100")) == rt(b"?")
    wco = "<Idle|MPos:0.000,0.000,0.000|FS:0,0|WCO:0.000,0.000,0.000>"
    assert grbl.feed(wco) == rt(b"?")  # `Ov:` is due next
    assert grbl.feed(ov("120,100,100")) == rt(b"\x91", b"?")
    assert grbl.feed(IDLE) == rt(b"?")
    assert grbl.feed(IDLE) == []  # no `Ov:`, no WCO: still 120, no nearer
    assert grbl.session.override_answers == 1
    assert grbl.session.model.overrides == {"feed": 120, "rapid": 100, "spindle": 100}
    assert grbl.feed(ov("120,100,100")) == [] and grbl.session.override_answers == 1


def test_an_override_gives_up_after_its_bound_of_rounds() -> None:
    """A board that moves, but by one a round (not a board's way, but a bound is one),
    is answered after OVERRIDE_ROUNDS rounds with what it said last."""
    grbl = Grbl()
    grbl.connect()
    grbl.session.override(feed=200)
    assert grbl.pump() == rt(b"\x90", b"\x91", b"?")
    rounds = 1
    feed = 100
    while True:
        assert grbl.feed(ov(f"{feed},100,100")) == rt(b"?")
        feed += 1
        out = grbl.feed(ov(f"{feed},100,100"))
        if not out:
            break
        assert out[0] == (Lane.REALTIME, b"\x91") and out[-1] == (Lane.REALTIME, b"?")
        rounds += 1
    assert rounds == OVERRIDE_ROUNDS == 20
    assert grbl.session.override_answers == 1
    assert grbl.session.model.overrides == {"feed": 120, "rapid": 100, "spindle": 100}


def test_an_override_under_way_when_the_board_resets_is_answered_with_its_100() -> None:
    """A reset sets every override to 100 (protocol.c; grblHAL flushes its rings): no more
    rounds, and the first report after it is the answer."""
    grbl = Grbl()
    grbl.connect()
    grbl.session.override(feed=150)
    grbl.pump()
    assert grbl.feed(ov("100,100,100")) == rt(b"?")
    grbl.feed("", "Grbl 1.1h ['$' for help]")
    grbl.feed("$N0=", "$N1=", "ok")
    grbl.feed("[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]", "ok")
    written = len(grbl.realtime())
    grbl.feed(ov("100,100,100"))
    assert grbl.session.override_answers == 1
    assert grbl.session.model.overrides == {"feed": 100, "rapid": 100, "spindle": 100}
    assert not [b for b in grbl.realtime()[written:] if b != b"?"]  # no override byte


def test_an_override_waiting_for_its_report_is_forgotten_with_the_link() -> None:
    grbl = Grbl()
    grbl.connect()
    grbl.session.override(feed=50)
    grbl.pump()
    grbl.session.close("unplugged")
    grbl.pump()
    grbl.connect()
    for _ in range(3):  # the new connection's reports ask nothing about the old request
        assert grbl.feed("<Idle|MPos:0.000,0.000,0.000|FS:0,0|Ov:100,100,100>") == []
    assert grbl.session.override_answers == 0


def _job(grbl: Grbl, count: int) -> Stream:
    lines = ((i, f"G1 X{i} F100") for i in range(1, count + 1))
    stream = Stream(job_id=1, encode=grbl.session.encode_job_line, numbered=True)
    stream.feed_all(lines)
    grbl.session.start_stream(stream)
    grbl.pump()
    return stream


def test_the_executing_line_comes_from_ln_else_from_what_the_planner_still_holds() -> None:
    grbl = Grbl()
    grbl.connect(opt="VN,15,128")  # built with USE_LINE_NUMBERS: `Ln:` may come
    stream = _job(grbl, 10)
    assert grbl.lines()[0] == b"N1 G1 X1 F100\n"
    grbl.feed(*["ok"] * 6)
    # A report without Ln: 3 of 15 blocks still planned, so lines 4-6 have not run.
    grbl.feed("<Run|MPos:1.000,0.000,0.000|Bf:12,100|FS:100,0>")
    assert stream.line_executed == 3
    grbl.feed("<Run|MPos:1.000,0.000,0.000|Bf:13,100|FS:100,0|Ln:5>")  # the board says it
    assert stream.line_executed == 5
    grbl.feed("<Run|MPos:1.000,0.000,0.000|Bf:15,100|FS:100,0|Ln:2>")  # never backwards
    assert stream.line_executed == 6  # the planner is empty: all six answered lines ran


def test_a_classic_build_without_line_numbers_is_sent_the_lines_as_they_are() -> None:
    """`[OPT:V,15,128]` (gnea/grbl's default: USE_LINE_NUMBERS off) means no `Ln:` will
    ever come: an N word would cost each line its bytes in the 128-byte buffer for
    nothing. The executing line is still bounded by `Bf:`, in file lines."""
    grbl = Grbl()
    grbl.connect()  # [OPT:V,15,128]
    assert not grbl.session.numbers_lines()
    stream = _job(grbl, 20)
    written = grbl.lines()
    assert written[:4] == [b"G1 X1 F100\n", b"G1 X2 F100\n", b"G1 X3 F100\n", b"G1 X4 F100\n"]
    # 9 lines of 11 bytes and 2 of 12 in 127; numbered (14 and 16 bytes), 9 would fit.
    assert len(written) == 11 and grbl.unanswered_bytes() == 9 * 11 + 2 * 12
    grbl.feed(*["ok"] * 6)
    grbl.feed("<Run|MPos:1.000,0.000,0.000|Bf:12,100|FS:100,0>")
    assert stream.line_executed == 3


@pytest.mark.parametrize(
    ("opt", "hal", "numbered"),
    [
        ("VN,15,128", False, True),  # classic, USE_LINE_NUMBERS
        ("VNM+,100,1024,3,0", True, True),  # grblHAL: always N (core report.c)
        ("V,15,128", False, False),  # classic's default build
    ],
)
def test_job_lines_are_numbered_only_for_a_board_that_reports_them(
    opt: str, hal: bool, numbered: bool
) -> None:
    grbl = Grbl()
    assert grbl.session.numbers_lines()  # before `$I` is read: numbered, as ever
    grbl.connect(opt=opt, hal=hal)
    assert grbl.session.numbers_lines() is numbered
    _job(grbl, 3)
    assert grbl.lines()[0] == (b"N1 G1 X1 F100\n" if numbered else b"G1 X1 F100\n")


def test_the_lockout_says_what_ends_it_on_grbl() -> None:
    grbl = Grbl()
    grbl.connect()
    assert grbl.session.lockout() is None
    grbl.feed("ALARM:9")  # homing failed: $X unlocks it
    assert grbl.session.lockout() == {
        "state": "ALARM",
        "message": grbl.session.model.last_exception_message(),
        "clear": "machine.clear",
    }
    assert "limit switch" in grbl.session.lockout()["message"]  # type: ignore[index]
    grbl.feed("ALARM:1")  # a hard limit: the board reads nothing until a reset
    assert grbl.session.lockout()["clear"] == "machine.reset, then machine.clear"  # type: ignore[index]
    grbl.feed("ALARM:10")  # grblHAL's e-stop: SHUTDOWN
    assert grbl.session.lockout()["state"] == "SHUTDOWN"  # type: ignore[index]
    assert grbl.session.lockout()["clear"] == "machine.reset, then machine.clear"  # type: ignore[index]


@pytest.mark.parametrize(
    ("homing", "homes"), [("1", True), ("3", True), ("0", False), ("nan", False)]
)
def test_a_grbl_that_homes_says_home_ends_its_alarm(homing: str, homes: bool) -> None:
    """gnea/grbl system.c takes `$H` in ALARM where `$22` bit 0 enables homing."""
    grbl = Grbl()
    grbl.connect(settings=(f"$22={homing}",))
    grbl.feed("ALARM:9")
    home = " or machine.home" if homes else ""
    assert grbl.session.lockout()["clear"] == "machine.clear" + home  # type: ignore[index]
    grbl.feed("ALARM:1")  # a hard limit: the reset first, then either
    want = f"machine.reset, then machine.clear{home}"
    assert grbl.session.lockout()["clear"] == want  # type: ignore[index]


# -- startup blocks (issue 24, part 3) ----------------------------------------------


def cancelled_at_rest(grbl: Grbl) -> Stream:
    stream = moves(50)
    grbl.session.start_stream(stream)
    grbl.pump()
    grbl.feed("ok", "<Run|MPos:1.000,0.000,0.000|FS:1000,0>")
    grbl.session.realtime(Realtime.JOB_KILL)
    grbl.pump()
    grbl.feed("<Hold:0|MPos:1.600,0.000,0.000|FS:0,0>")
    return stream


def test_the_startup_blocks_are_read_at_connect_and_shown_with_what_they_do() -> None:
    grbl = Grbl()
    grbl.connect(startup=("G54G21", "G0X-100"))
    blocks = grbl.session.model.snapshot()["startup_blocks"]
    assert blocks == [
        {"n": 0, "line": "G54G21", "acts": None},
        {"n": 1, "line": "G0X-100", "acts": "moves the machine (G0)"},
    ]


def test_a_cancel_holds_instead_of_resetting_while_a_startup_block_moves() -> None:
    grbl = Grbl()
    grbl.connect(startup=("", "X-100"))
    stream = cancelled_at_rest(grbl)
    assert stream.result.end is StreamEnd.CANCELLED
    assert codec.RESET not in grbl.realtime()  # the block would run: no reset of ours
    (held,) = [e for e in grbl.events if isinstance(e, Excepted)]
    assert "held instead of reset" in held.fields["msg"] and "$N1=X-100" in held.fields["msg"]
    assert grbl.session.model.snapshot()["last_exception"] == held.fields
    assert not grbl.session.quiet()  # the machine stays busy: the board still holds the job
    with pytest.raises(Busy, match=r"machine\.reset runs it"):
        grbl.session.realtime(Realtime.CYCLE_START)  # `~` would run the cancelled moves
    with pytest.raises(Busy, match="held instead of reset"):
        grbl.session.send("G0 X1", object())
    grbl.session.reset()  # the operator's reset: asked for, it goes
    grbl.pump()
    assert grbl.realtime()[-1] == codec.RESET


def test_a_stop_timeout_holds_too_while_a_startup_block_starts_the_spindle() -> None:
    grbl = Grbl()
    grbl.connect(startup=("M3S1000", ""))
    grbl.feed("<Run|MPos:1.000,0.000,0.000|FS:1000,0>")
    grbl.session.realtime(Realtime.QUEUE_FLUSH)
    grbl.pump()
    grbl.at(STOP_TIMEOUT)
    assert codec.RESET not in grbl.realtime()
    assert "starts the spindle or laser (M3)" in grbl.session.model.last_exception["msg"]


def test_startup_motion_allowed_resets_as_usual() -> None:
    grbl = Grbl(startup_motion=True)
    grbl.connect(startup=("G0X-100", ""))
    cancelled_at_rest(grbl)
    assert grbl.realtime()[-1] == codec.RESET


def test_a_reset_reads_the_startup_blocks_again() -> None:
    grbl = Grbl()
    grbl.connect(startup=("G0X-100", ""))
    grbl.session.reset()
    grbl.pump()
    grbl.feed("Grbl 1.1h ['$' for help]", "$N0=", "$N1=", "ok")  # `$RST=*` cleared them
    grbl.feed("[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]", "ok", IDLE)
    assert grbl.session.ready and grbl.session.model.startup_blocks == []
    cancelled_at_rest(grbl)
    assert grbl.realtime()[-1] == codec.RESET


@pytest.mark.parametrize("byte", range(256))
def test_a_job_line_reaches_grbl_only_with_bytes_it_reads_as_part_of_a_line(
    byte: int,
) -> None:
    """Every character, in a job line: written as it is, or refused saying why (codec.encode)."""
    line = f"G1 X1{chr(byte)}2 S4"
    if 0x20 <= byte <= 0x7E and chr(byte) not in "?!~(;":
        assert codec.encode(line) == line.encode() + b"\n"
        return
    if chr(byte) in "(;":
        assert codec.encode(line) == b"G1 X1\n"  # a comment to the end of the line, dropped
        return
    with pytest.raises(InvalidCommand) as caught:
        codec.encode(line)
    printable = 0x20 <= byte <= 0x7E
    assert caught.value.refusal is (Refusal.REALTIME if printable else Refusal.NOT_TEXT)


def test_a_line_one_byte_over_the_receive_buffer_is_refused() -> None:
    fits = "G1 X" + "1" * 122  # 126 bytes and its LF: 127, the most grbl's 128 holds
    assert codec.encode(fits) == fits.encode() + b"\n"
    with pytest.raises(InvalidCommand) as caught:
        codec.encode(fits + "1")
    assert caught.value.refusal is Refusal.TOO_LONG


@pytest.mark.parametrize(
    "state", [S.RUN, *(s for s in S if s.is_lockout), S.HOLD, S.INTERLOCK], ids=lambda s: s.name
)
def test_no_job_line_is_written_in_a_lockout_a_hold_or_a_door_even_before_its_drain(
    state: S,
) -> None:
    """The job's gate (`_job_lines_wait`, `_pump`'s and the express step's): while the
    model says ALARM, SHUTDOWN, PANIC, HOLD or a door open, an `ok` that frees the
    receive buffer writes no line of the job. In RUN the same `ok` writes the next."""
    grbl = streaming()
    stream = grbl.session.stream
    assert stream is not None
    sent = stream.sent
    grbl.session.model.state = state  # as a report has just set it
    grbl.feed("ok")
    assert (stream.sent > sent) is (state is S.RUN)
