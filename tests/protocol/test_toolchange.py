"""A program's M6 lines, read as text, and what each dialect sends once the host handled them."""

from __future__ import annotations

import pytest

from hostd.protocol.toolchange import has_m6, tool_words, without_m6
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
