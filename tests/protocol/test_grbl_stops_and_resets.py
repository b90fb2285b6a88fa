"""grbl's session: a stop empties the board by a reset, and a reset leaves the books clean.

A stop (a cancel, a failed job) is a feedhold, then a soft reset once motion
rests (docs/dialects.md, grbl's Stopping row). Guarded here by the bytes on
the wire: a resume kept back before the stop never follows it (a `~` would
run the moves being cancelled); a stop asked while a reset is under way adds
no feedhold (the board would boot into a hold); a job line refused with a
lockout's error stops the board even when no ALARM was read; a stop held
instead of reset (a startup block that moves) writes nothing more; and after
any reset, ours or the board's own, the receive buffer, an EEPROM write and a
stop under way are forgotten, and an internal fault ends: lines go again.
"""

from __future__ import annotations

from hostd.protocol.commands import Realtime
from hostd.protocol.errors import ControllerError
from hostd.protocol.grbl import codec
from hostd.protocol.grbl.stops import STOP_TIMEOUT
from hostd.protocol.stream import Stream
from hostd.protocol.vocabulary import Lane, StreamEnd
from tests.protocol.test_grbl_session import IDLE, Grbl, moves

HOLD_0 = "<Hold:0|MPos:1.600,0.000,0.000|FS:0,0>"


def running(grbl: Grbl, lines: int = 50) -> Stream:
    """Connect and run a job of `lines` moves, its first line answered."""
    grbl.connect()
    stream = moves(lines)
    grbl.session.start_stream(stream)
    grbl.pump()
    grbl.feed("ok", "<Run|MPos:1.000,0.000,0.000|FS:1000,0>")
    return stream


def resync(grbl: Grbl) -> None:
    """The board's banner after a reset, and the re-sync's answers (`$N`, `$G`, `?`)."""
    grbl.feed("", "Grbl 1.1h ['$' for help]")
    grbl.feed("$N0=", "$N1=", "ok")
    grbl.feed("[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]", "ok", IDLE)
    assert grbl.session.ready


def test_a_resume_kept_back_before_a_cancel_never_follows_it() -> None:
    """Pause, resume while the hold decelerates (the `~` is kept for Hold:0), then
    cancel: the hold completing must bring the stop's reset, never the kept `~`."""
    grbl = Grbl()
    stream = running(grbl)
    grbl.session.pause_stream()
    grbl.session.resume_stream()  # kept: the hold is not complete yet
    grbl.session.realtime(Realtime.JOB_KILL)
    grbl.pump()
    assert stream.result is not None and stream.result.end is StreamEnd.CANCELLED
    grbl.feed("<Hold:1|MPos:1.500,0.000,0.000|FS:500,0>")
    grbl.feed(HOLD_0)
    grbl.feed(HOLD_0)
    assert codec.CYCLE_START not in grbl.realtime()
    assert grbl.realtime()[-1] == codec.RESET


def test_a_stop_asked_while_a_reset_is_under_way_writes_no_feedhold() -> None:
    """The reset empties the board already; a `!` read as it boots would hold it."""
    grbl = Grbl()
    running(grbl)
    grbl.session.reset()
    grbl.pump()
    grbl.session.realtime(Realtime.QUEUE_FLUSH)
    assert grbl.pump() == []
    assert codec.FEEDHOLD not in grbl.realtime()
    resync(grbl)
    grbl.at(STOP_TIMEOUT + 1)
    assert grbl.realtime().count(codec.RESET) == 1


def test_a_lockout_error_for_a_job_line_stops_the_board_when_no_alarm_was_read() -> None:
    """error:9 with no ALARM seen (its line lost on the wire): the lines behind the
    refused one are in the board's buffer and would run, so the board is stopped."""
    grbl = Grbl()
    stream = running(grbl)
    grbl.feed("error:9")
    assert stream.result is not None and stream.result.end is StreamEnd.FAILED
    assert stream.result.code == ControllerError.code
    assert grbl.realtime()[-2:] == [codec.FEEDHOLD, codec.STATUS]


def test_a_stop_held_instead_of_reset_writes_nothing_more() -> None:
    """A startup block would move the machine at a reset: the board stays held with the
    cancelled job's moves in it, and no line waiting since the stop goes to it."""
    grbl = Grbl()
    grbl.connect(startup=("", "G0X-100"))
    stream = moves(50)
    grbl.session.start_stream(stream)
    grbl.pump()
    grbl.feed("ok", "<Run|MPos:1.000,0.000,0.000|FS:1000,0>")
    grbl.session.realtime(Realtime.JOB_KILL)
    grbl.pump()
    lines = len(grbl.lines())
    grbl.session.send("$#", object())  # a query waits while the stop is under way
    grbl.feed(HOLD_0)  # at rest: held, not reset
    assert codec.RESET not in grbl.realtime()
    grbl.feed("ok", "ok", HOLD_0)
    assert len(grbl.lines()) == lines
    assert not grbl.session.quiet()


def test_a_reset_mid_job_frees_the_whole_receive_buffer() -> None:
    grbl = Grbl()
    running(grbl)
    assert grbl.unanswered_bytes() > 64  # the job's lines fill the buffer
    grbl.session.reset()
    grbl.pump()
    resync(grbl)
    line = "G1 X" + "1".rjust(122, "0")  # 127 bytes with its LF: the whole ring
    grbl.session.send(line, object())
    assert grbl.pump() == [(Lane.DATA, (line + "\n").encode())]


def test_a_reset_while_a_setting_is_written_lets_lines_go_after_it() -> None:
    """The setting's answer never comes (the reset forgot it): nothing waits for it."""
    grbl = Grbl()
    grbl.connect()
    grbl.session.send("$110=600", object())
    grbl.pump()
    grbl.session.reset()
    grbl.pump()
    resync(grbl)
    grbl.session.send("$$", object())
    assert grbl.pump() == [(Lane.DATA, b"$$\n")]


def test_a_board_that_resets_itself_during_a_stop_ends_the_stop() -> None:
    """The banner says the board is empty: no second reset at the stop's timeout,
    and lines go again once it is re-synced."""
    grbl = Grbl()
    running(grbl)
    grbl.session.realtime(Realtime.JOB_KILL)
    grbl.pump()
    grbl.feed("<Hold:1|MPos:1.500,0.000,0.000|FS:500,0>")  # decelerating: no reset yet
    resync(grbl)  # the board's own reset
    grbl.session.send("$$", object())
    assert grbl.pump() == [(Lane.DATA, b"$$\n")]
    grbl.at(STOP_TIMEOUT + 1)
    assert codec.RESET not in grbl.realtime()


def test_machine_reset_ends_an_internal_fault() -> None:
    grbl = Grbl()
    grbl.connect()
    grbl.session.halt("books out of step")
    grbl.session.reset()
    grbl.pump()
    resync(grbl)
    grbl.session.send("$$", object())
    assert grbl.pump() == [(Lane.DATA, b"$$\n")]
