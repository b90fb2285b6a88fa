"""Job files to sendable lines: what is stripped, what is kept, which line numbers."""

from __future__ import annotations

from collections.abc import Iterator

from hostd.protocol.program import program_lines, strip_line

PROGRAM = """\
%
(sample part)
G21 G90 ; metric, absolute

G0 X10 Y10 (rapid to start)
G1 X20 F600
   ; only a comment
%
M30
"""


def test_comments_blanks_and_tape_marks_are_stripped_with_line_numbers_kept() -> None:
    assert list(program_lines(PROGRAM.splitlines())) == [
        (3, "G21 G90"),
        (5, "G0 X10 Y10"),
        (6, "G1 X20 F600"),
        (9, "M30"),
    ]


def test_start_line_skips_what_comes_before_it() -> None:
    assert list(program_lines(PROGRAM.splitlines(), start_line=6)) == [
        (6, "G1 X20 F600"),
        (9, "M30"),
    ]


def test_unclosed_comment_runs_to_the_end_of_the_line() -> None:
    assert strip_line("G1 X1 (never closed") == "G1 X1"


def test_lines_keep_their_inner_spacing_and_case() -> None:
    assert strip_line("  g1 x1  y2\t") == "g1 x1  y2"


def test_streams_lazily() -> None:
    def endless() -> Iterator[str]:
        n = 0
        while True:
            n += 1
            yield f"G1 X{n}"

    lines = program_lines(endless())
    assert next(lines) == (1, "G1 X1")
    assert next(lines) == (2, "G1 X2")
