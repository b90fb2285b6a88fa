"""A program's M6 lines, read as text, and what each dialect sends once the host handled them."""

from __future__ import annotations

from typing import Any

import pytest

from hostd.protocol.errors import Busy
from hostd.protocol.grbl import codec
from hostd.protocol.stream import Stream
from hostd.protocol.toolchange import Modes, has_m6, tool_words, without_m6
from hostd.protocol.vocabulary import Detected, Lane, StreamEnd
from tests.protocol.g2wire import Wire
from tests.protocol.test_grbl_session import Grbl


@pytest.mark.parametrize("line", ["M6", "T2 M6", "M06 T2", "m 6", "G0 Z5 M6 T3", "T1M6"])
def test_an_m6_however_it_is_spelled(line: str) -> None:
    assert has_m6(line)


@pytest.mark.parametrize("line", ["M60", "M61 Q1", "M6.1", "G0 X6", "M3 S6000", "T6", "G0 X1M62"])
def test_no_m6_where_there_is_none(line: str) -> None:
    assert not has_m6(line)


def test_the_tool_words_and_the_line_without_its_m6() -> None:
    assert tool_words("T2 M6") == [2] and tool_words("G0 X1") == [] and tool_words("t 07") == [7]
    assert without_m6("T2 M6") == "T2"
    assert without_m6("G0 Z5 M06 T3") == "G0 Z5 T3"
    assert without_m6("M6") == "" and without_m6("N40 M6") == ""


def test_a_long_line_of_almost_m6_is_read_in_linear_time() -> None:
    line = "M" + " " * 100_000 + "0" * 100_000 + "7"
    assert not has_m6(line) and without_m6(line) == line.replace(" " * 100_000, " ").strip()


def test_grbl_never_gets_the_m6_but_keeps_the_tool() -> None:
    session = Grbl().session
    assert session.tool_change_line("T2 M6", 2) == "T2"
    assert session.tool_change_line("M6", 2) == "T2"  # a line of M6 alone: still a line
    assert session.tool_length_lines(2, -1.25) == ["G43.1 Z-1.2500"]


def test_g2core_takes_the_m6_and_sets_the_offset_through_its_tool_table() -> None:
    session = Wire().session
    assert session.tool_change_line("T2 M6", 2) == "T2 M6"
    assert session.tool_length_lines(2, 3.5) == ["G10 L1 P2 Z3.5000", "G43 H2"]


# -- the hold point: the session's Stream holds before an M6 line (stream.py) -----------


def _held_job(encode: Any = None, *, ended: bool = True) -> Stream:
    """Four lines; the third (the M6 line) is a hold point. Not `ended`: the file has
    more lines, not fed yet."""
    stream = Stream(job_id=1, encode=encode)
    stream.feed(1, "G1 X1 F600")
    stream.feed(2, "G1 X2")
    stream.feed(3, "T2 M6", hold=True)
    stream.feed(4, "G1 X3")
    if ended:
        stream.end_of_input()
    return stream


def test_g2core_holds_before_the_m6_line_and_takes_the_stop_for_no_underflow() -> None:
    wire = Wire(window=4)
    wire.connect()
    stream = _held_job(ended=False)  # a long file: more lines on the host
    wire.session.start_stream(stream)
    wire.pump()
    assert [line for line in wire.lines(Lane.DATA) if b"X" in line] == [
        b"G1 X1 F600\n",
        b"G1 X2\n",
    ]
    assert stream.held == 3 and not stream.lines_on_host()
    wire.report(stat=5)
    wire.answer_all()
    wire.report(stat=3)  # the board ran all it had: a stop, with the rest held on the host
    assert wire.of(Detected) == [] and not stream.done
    assert len(wire.lines(Lane.DATA)) == 2  # nothing past the hold
    wire.session.release_stream()
    wire.pump()
    assert wire.lines(Lane.DATA)[2:] == [b"T2 M6\n", b"G1 X3\n"] and stream.held is None


def test_g2core_resumed_at_an_m6_takes_a_stop_before_it_is_read_for_no_underflow() -> None:
    """A job resumed at its M6 (job.recovery after a lost link): its preamble moves
    nothing, so the board stops at once, maybe before the host has read the M6 line
    from the file. No underflow: the board never moved (behaviour.md, faults)."""
    wire = Wire(window=4)
    wire.connect()
    wire.report(stat=3, posx=0, posy=0, posz=0, mpox=0, mpoy=0, mpoz=0, vel=0)
    stream = Stream()
    for line in ("G21 G90", "G0 X0 Y0", "G1 Z0 F300"):
        stream.feed(0, line)  # the preamble and approach: file line 0
    wire.session.start_stream(stream)
    wire.pump()
    assert stream.lines_on_host()  # the M6 line not read yet: the host looks late
    wire.report(stat=5)
    wire.answer_all()
    wire.report(stat=3)
    assert wire.of(Detected) == [] and not stream.done
    stream.feed(3, "T1 M6", hold=True)
    stream.feed(4, "G0 X1")
    wire.pump()
    assert stream.held == 3


def test_a_users_resume_never_carries_a_job_past_its_hold() -> None:
    grbl = Grbl()
    grbl.connect()
    stream = _held_job(lambda text, _n: codec.encode(text))
    grbl.session.start_stream(stream)
    grbl.pump()
    assert grbl.lines() == [b"G1 X1 F600\n", b"G1 X2\n"] and stream.held == 3
    grbl.session.pause_stream()
    grbl.feed("ok", "ok", "<Hold:0|MPos:2.000,0.000,0.000|FS:0,0>")
    grbl.session.resume_stream()  # `~`: the user's pause ends, the hold stays
    grbl.feed("<Idle|MPos:2.000,0.000,0.000|FS:0,0>")
    assert grbl.realtime()[-2:] == [b"~", b"?"] and len(grbl.lines()) == 2 and stream.held == 3
    with pytest.raises(Busy):
        grbl.session.resume_stream()  # not paused: no `~` to send
    grbl.session.release_stream()
    grbl.pump()
    assert grbl.lines()[2:] == [b"T2 M6\n", b"G1 X3\n"]
    with pytest.raises(Busy, match="not held"):
        grbl.session.release_stream()
    grbl.feed("ok", "ok", "<Idle|MPos:3.000,0.000,0.000|FS:0,0>")
    grbl.feed("<Idle|MPos:3.000,0.000,0.000|FS:0,0>")
    assert stream.done and stream.result is not None and stream.result.end is StreamEnd.COMPLETED


def test_a_job_that_ends_while_held_drops_its_hold() -> None:
    grbl = Grbl()
    grbl.connect()
    stream = _held_job(lambda text, _n: codec.encode(text))
    grbl.session.start_stream(stream)
    grbl.pump()
    grbl.session.stop_stream(1007, "fault active: estop")
    assert stream.done and stream.held is None
    with pytest.raises(Busy):
        grbl.session.release_stream()


def test_the_programs_spindle_as_its_lines_leave_it() -> None:
    modes = Modes()
    assert modes.spindle_lines(2.0) == []  # off: nothing to turn back on
    modes = modes.after("G1 X1 M03 S8000 F300")
    assert modes.spinning and modes.spindle_lines(2.0) == ["M3 S8000", "G4 P2"]
    assert modes.after("S12000").spindle_lines(0.25) == ["M3 S12000", "G4 P0.25"]
    assert modes.after("M4").spindle_lines(0.0) == ["M4 S8000"]  # a laser: no dwell
    assert modes.after("M30").spinning  # a program end is no spindle word
    assert not modes.after("M5").spinning and not modes.after("m 05").spinning


def test_the_modes_put_back_after_a_measurement() -> None:
    modes = Modes().after("G20 G91 G18 G55 G02 X1 Y1 I1 F30").after("g 00 x2")
    assert modes.lines() == ["G20 G91 G18 G55 G0 F30"]
    # An arc cannot be selected without a move: G1 (a feed) stands in; G38.x is left.
    assert Modes().after("G03 X1 I1 F9").lines() == ["G21 G90 G1 F9"]
    assert Modes().after("G38.20 Z-5").lines() == ["G21 G90"]
    assert Modes().after("G1 X1 G59.1 G17").after("G80").lines() == ["G21 G90 G17 G59.1 G80"]
    # G53, G28, G92, G90.1 are no mode to put back; G0 of N10 or X10 is no G word.
    assert Modes().after("N10 G53 G28 G92 G90.1 X10").lines() == ["G21 G90"]


def test_reading_the_modes_of_a_long_line_takes_linear_time() -> None:
    line = "G" + "0" * 200_000 + "G1.5" * 50_000
    assert Modes().after(line).motion == "G0"
