"""grbl's session: when a line may reach the board, byte by byte on the wire.

Each test pins one gate of `GrblFlow._pump` and `send` (docs/dialects.md,
grbl's column) by what is written, or refused, at the moment the rule says
nothing may go: a client's lines never overfill the 128-byte receive buffer;
nothing but a report's `?` goes while a stop or a reset is under way, nor
anything at all once the session has halted on an internal fault; a paused
job writes no line until it is resumed; an unlock waits for a report after
the alarm and for every line written before it; and after a critical alarm
the board, which reads nothing until it is reset, is sent nothing.
"""

from __future__ import annotations

import pytest

from hostd.protocol.commands import Realtime
from hostd.protocol.errors import FaultActive, Rejected
from hostd.protocol.vocabulary import Lane, Settled
from tests.protocol.test_grbl_session import Grbl, moves


def move(chars: int) -> str:
    """A move of exactly `chars` characters (its line is one byte more: the LF)."""
    return "G1 X" + "1".rjust(chars - 4, "0")


def test_a_clients_lines_fill_the_receive_buffer_to_127_bytes_and_never_to_128() -> None:
    """A ring of 128 bytes holds 127: a client's line that would be the 128th byte
    unanswered waits for an answer, one that is the 127th goes at once."""
    grbl = Grbl()
    grbl.connect()
    grbl.session.send(move(63), object())  # 64 bytes
    grbl.session.send(move(62), object())  # 63 bytes: 127 in all
    grbl.session.send("G4 P0", object())
    assert grbl.lines() == [] and len(grbl.pump()) == 2
    assert grbl.unanswered_bytes() == 127
    grbl.feed("ok")
    assert grbl.lines()[-1] == b"G4 P0\n"

    grbl = Grbl()
    grbl.connect()
    grbl.session.send(move(63), object())
    grbl.session.send(move(63), object())  # 128 in all: one byte would be lost
    assert [line for _, line in grbl.pump()] == [(move(63) + "\n").encode()]
    grbl.feed("ok")
    assert grbl.lines()[-1] == (move(63) + "\n").encode()


def test_no_line_goes_while_a_stop_waits_for_rest_or_a_reset_for_its_banner() -> None:
    """A stop's reset, or the operator's, throws away what the board holds: a line
    written meanwhile would be lost with it, or read half-way through the reset."""
    grbl = Grbl()
    grbl.connect()
    grbl.session.start_stream(moves(50))
    grbl.pump()
    grbl.feed("ok", "<Run|MPos:1.000,0.000,0.000|FS:1000,0>")
    grbl.session.realtime(Realtime.QUEUE_FLUSH)  # a cancel: `!`, then a reset at rest
    grbl.pump()
    lines = len(grbl.lines())
    grbl.session.send("$#", object())  # a query: admitted in any state
    grbl.feed("ok", "ok")
    grbl.feed("<Hold:1|MPos:1.500,0.000,0.000|FS:500,0>")
    assert len(grbl.lines()) == lines
    grbl.feed("<Hold:0|MPos:1.600,0.000,0.000|FS:0,0>")
    assert grbl.realtime()[-1] == b"\x18" and len(grbl.lines()) == lines

    grbl = Grbl()
    grbl.connect()
    grbl.session.reset()
    grbl.session.send("$$", object())
    assert grbl.pump() == [(Lane.REALTIME, b"\x18")]  # and nothing until the banner
    grbl.feed("ok")
    assert grbl.lines() == []


def test_a_halted_session_writes_nothing_but_a_hold_and_a_reset() -> None:
    """An internal fault: no line is written, not even one that was waiting already,
    until machine.reset; a client's line is refused with the fault, a `!` still goes."""
    grbl = Grbl()
    grbl.connect()
    grbl.session.send("$110=600", object())
    waiting = object()
    grbl.session.send("$$", waiting)  # waits for the setting's answer (EEPROM)
    assert grbl.pump() == [(Lane.DATA, b"$110=600\n")]
    grbl.session.halt("books out of step")
    grbl.feed("ok")
    assert grbl.lines() == [b"$110=600\n"]
    with pytest.raises(FaultActive):
        grbl.session.send("$G", object())
    with pytest.raises(FaultActive):
        grbl.session.realtime(Realtime.CYCLE_START)  # a `~` could start motion: refused
    grbl.session.realtime(Realtime.FEEDHOLD)
    assert grbl.pump()[0] == (Lane.REALTIME, b"!")
    assert grbl.lines() == [b"$110=600\n"]
    assert b"~" not in grbl.realtime()


def test_a_paused_job_writes_no_line_before_a_report_shows_the_hold() -> None:
    """classic grbl plans lines read while its hold decelerates: a pause stops the job's
    lines at once, not when the next report says Hold."""
    grbl = Grbl()
    grbl.connect()
    grbl.session.start_stream(moves(50))
    grbl.pump()
    grbl.feed("<Run|MPos:1.000,0.000,0.000|FS:1000,0>")
    grbl.session.pause_stream()
    grbl.pump()
    written = len(grbl.lines())
    grbl.feed("ok", "ok")  # answers read before any report of the hold
    assert len(grbl.lines()) == written


def test_an_unlock_waits_for_a_report_after_the_alarm() -> None:
    """Nothing of the host's follows an ALARM until a report says where the board is."""
    grbl = Grbl()
    grbl.connect()
    grbl.feed("ALARM:9")  # a homing failure: `$X` leaves it
    token = object()
    assert grbl.session.clear(token)
    grbl.pump()
    assert grbl.lines() == []
    grbl.feed("<Alarm|MPos:0.000,0.000,0.000|FS:0,0>")
    assert grbl.lines() == [b"$X\n"]


def test_an_unlock_waits_for_the_lines_written_before_it_to_be_answered() -> None:
    """A line still in the board's buffer would run after the `$X` that unlocks it."""
    grbl = Grbl()
    grbl.connect()
    move_token = object()
    grbl.session.send("G0 X1", move_token)
    grbl.pump()
    grbl.feed("ALARM:9", "<Alarm|MPos:0.000,0.000,0.000|FS:0,0>")
    assert grbl.session.clear(object())
    grbl.pump()
    assert grbl.lines() == [b"G0 X1\n"]
    grbl.feed("error:9")  # the move, refused by the alarm
    assert isinstance(grbl.settled(move_token), Settled)
    assert grbl.lines() == [b"G0 X1\n", b"$X\n"]


@pytest.mark.parametrize("line", ["$X", "$H", "$$"])
def test_after_a_critical_alarm_no_line_is_sent_until_a_reset(line: str) -> None:
    """A hard limit (ALARM:1): classic grbl reads no line at all until it is reset,
    so even an unlock or a query sent as a line is refused on the host."""
    grbl = Grbl()
    grbl.connect()
    grbl.feed("ALARM:1", "<Alarm|MPos:0.000,0.000,0.000|FS:0,0>")
    with pytest.raises(Rejected, match="reads nothing until a reset"):
        grbl.session.send(line, object())
    grbl.session.reset()
    grbl.pump()
    grbl.feed("", "Grbl 1.1h ['$' for help]", "$N0=", "ok", "[GC:G0 G54]", "ok")
    grbl.feed("<Alarm|MPos:0.000,0.000,0.000|FS:0,0>")
    grbl.session.send(line, object())
    grbl.pump()
    assert grbl.lines()[-1] == f"{line}\n".encode()
