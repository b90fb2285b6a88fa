"""A job's line stream on g2core: hold points, program pauses, and its one outcome.

Pins stream.py's rules as the board and the operator see them: a job stops
at a hold point (a tool change) and writes nothing past it until released,
then goes on with the next line; a board that stops there, or at an M0 the job
sent, is not starved (no underflow fault); and a job's outcome is set once:
what ends it later does not rewrite it nor tell its end again.
"""

from __future__ import annotations

import pytest

from hostd.protocol.stream import Stream
from hostd.protocol.vocabulary import Detected, Lane, StreamEnd, StreamEnded
from tests.protocol.g2wire import BUILDS, Wire

LIMIT = '{"er":{"fb":%s,"st":203,"msg":"Limit hit - input 1"}}'


def ready(fb: float) -> Wire:
    wire = Wire(fb)
    wire.connect()
    return wire


def tool_change_job() -> Stream:
    """Two moves, a hold point before line 3 (the M6), three more moves; more to come (the
    caller has not read the whole file)."""
    stream = Stream(job_id=1)
    stream.feed(1, "G1 X1 F1000")
    stream.feed(2, "G1 X2 F1000")
    stream.feed(3, "M6 T2", hold=True)
    for number in (4, 5, 6):
        stream.feed(number, f"G1 X{number} F1000")
    return stream


def underflows(wire: Wire) -> list[Detected]:
    return [d for d in wire.of(Detected) if d.fault == "underflow"]


@pytest.mark.parametrize("fb", BUILDS)
def test_a_job_waits_at_its_hold_point_then_goes_on_once_released(fb: float) -> None:
    wire = ready(fb)
    stream = tool_change_job()
    wire.session.start_stream(stream)
    wire.pump()
    wire.answer_all()
    assert wire.lines() == [b"G1 X1 F1000\n", b"G1 X2 F1000\n"]
    assert stream.held == 3
    wire.report(stat=5, posx=2, vel=100)
    wire.report(stat=3, posx=2, vel=0)  # the board stops at the tool change
    assert underflows(wire) == []  # held on purpose: nothing starved
    wire.session.release_stream(tool=2)
    wire.pump()
    assert stream.held is None
    assert wire.lines()[2] == b"M6 T2\n"
    wire.answer_all()
    assert wire.lines(Lane.DATA)[3:] == [b"G1 X4 F1000\n", b"G1 X5 F1000\n", b"G1 X6 F1000\n"]


@pytest.mark.parametrize("fb", BUILDS)
def test_an_m0_written_behind_a_jobs_json_line_is_a_pause_not_an_underflow(fb: float) -> None:
    """A `{`-line waits for the lines before it and is written on its own, with the lines
    behind it one at a time: the M0 among them still marks the stop as the program's."""
    wire = ready(fb)
    texts = ["G1 X1 F1000", '{"out4":1}', "M0", *(f"G1 X{i} F1000" for i in range(2, 12))]
    stream = Stream(job_id=1).feed_all(enumerate(texts, start=1))
    wire.session.start_stream(stream)
    wire.pump()
    wire.report(stat=5, posx=0.5, vel=100)  # the board runs the first move
    assert b"M0\n" not in wire.lines()
    wire.answer(b"G1 X1 F1000\n", {})
    assert b"M0\n" in wire.lines()
    wire.report(stat=3, posx=1, vel=0)  # M0: the program pauses
    assert underflows(wire) == []


@pytest.mark.parametrize("fb", BUILDS)
def test_a_jobs_outcome_is_set_once(fb: float) -> None:
    """A job failed by a refused line, then caught by an alarm: its end stays the first
    one, told once."""
    wire = ready(fb)
    stream = Stream(job_id=1).feed_all((i, f"G1 X{i} F1000") for i in range(1, 11))
    wire.session.start_stream(stream)
    wire.pump()
    wire.answer(wire.unanswered[0], {}, status=108)
    assert stream.result is not None and stream.result.code != 204
    first = stream.result
    wire.feed(LIMIT % fb)
    wire.answer_all()
    wire.report(stat=2)
    assert stream.result == first
    assert len(wire.of(StreamEnded)) == 1
    assert stream.result.end is StreamEnd.FAILED


@pytest.mark.parametrize("fb", BUILDS)
def test_an_m0_in_the_first_window_is_a_pause_not_an_underflow(fb: float) -> None:
    """The job's first window goes out before the board's first report, M0 with it: the
    RUN reports that follow (the moves before it) do not undo it, and the stop at the M0
    is the program's pause, not an underflow (until 2026-11-29 a RUN report cleared the
    M0's mark, and the pause was told as a fault of the job's severity)."""
    wire = ready(fb)
    texts = ["G1 X1 F1000", "M0", *(f"G1 X{i} F1000" for i in range(2, 12))]
    stream = Stream(job_id=1).feed_all(enumerate(texts, start=1))
    wire.session.start_stream(stream)
    wire.pump()
    assert b"M0\n" in wire.lines()
    wire.answer(b"G1 X1 F1000\n", {})
    wire.report(stat=5, posx=0.5, vel=100)  # read after the M0 was written
    wire.answer(b"M0\n", {})
    wire.report(stat=3, posx=1, vel=0)  # M0: the program pauses
    assert underflows(wire) == []


@pytest.mark.parametrize("fb", BUILDS)
def test_each_m0_in_flight_is_a_pause_and_a_stop_after_them_is_an_underflow(fb: float) -> None:
    """Two M0s out at once are two pauses; once the board runs on from the second, a
    stop with lines still on the host is the host starving it, told as an underflow."""
    wire = ready(fb)
    texts = ["G1 X1 F1000", "M0", "G1 X2 F1000", "M0", *(f"G1 X{i} F1000" for i in range(3, 40))]
    stream = Stream(job_id=1).feed_all(enumerate(texts, start=1))
    wire.session.start_stream(stream)
    wire.pump()
    assert wire.lines().count(b"M0\n") == 2
    wire.report(stat=5, posx=0.5, vel=100)
    for line in (b"G1 X1 F1000\n", b"M0\n"):
        wire.answer(line, {})
    wire.report(stat=3, posx=1, vel=0)  # the first M0
    wire.report(stat=5, posx=1.5, vel=100)  # cycle start
    for line in (b"G1 X2 F1000\n", b"M0\n"):
        wire.answer(line, {})
    wire.report(stat=3, posx=2, vel=0)  # the second M0
    assert underflows(wire) == []
    wire.report(stat=5, posx=2.5, vel=100)  # cycle start: no M0 left in flight
    wire.report(stat=3, posx=3, vel=0)  # stopped, lines still on the host
    assert len(underflows(wire)) == 1
