"""Job lines carry their file line number; the board's report of it is a lower bound."""

from __future__ import annotations

from hostd.protocol.program import MAX_LINE_NUMBER, number_line
from hostd.protocol.stream import Stream


def test_a_line_gets_its_file_line_number_in_place_of_its_own() -> None:
    assert number_line("G1 X1", 12) == "N12 G1 X1"
    assert number_line("N0100 G1 X1", 12) == "N12 G1 X1"  # two N words are an error
    assert number_line("n5G0X0", 7) == "N7 G0X0"
    assert number_line("G21", 0) == "N0 G21"  # a resume's preamble: line 0


def test_lines_that_are_not_gcode_and_numbers_too_big_stay_as_they_are() -> None:
    assert number_line("$H", 3) == "$H"
    assert number_line('{"sr":null}', 3) == '{"sr":null}'
    assert number_line("G1 X1", MAX_LINE_NUMBER + 1) == "G1 X1"


def _stream(lines: list[tuple[int, str]]) -> Stream:
    stream = Stream(1, lambda text, n: f"{n}:{text}".encode(), numbered=True).feed_all(lines)
    for _ in lines:
        assert stream.peek() is not None
        stream.take()
    return stream


def test_line_executed_only_moves_forward_within_the_lines_sent() -> None:
    stream = _stream([(0, "G21"), (10, "G1 X1"), (11, "G1 X2"), (14, "G1 X3")])
    stream.executing(9)  # a number from before this job (a previous job's, stale)
    assert stream.line_executed is None
    stream.executing(15)  # ahead of what was sent: not this job's
    assert stream.line_executed is None
    stream.executing(11)
    stream.executing(10)  # an older report arriving late
    assert stream.line_executed == 11


def test_acked_lines_are_remembered_for_the_planner_bound() -> None:
    stream = _stream([(3, "G1 X1"), (5, "G1 X2"), (8, "G1 X3")])
    for line in (3, 5, 8):
        stream.acknowledged(line)
    assert [stream.acked_line(k) for k in range(4)] == [8, 5, 3, None]
