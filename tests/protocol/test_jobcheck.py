"""What job.start refuses in a program, by plain calls (protocol/jobcheck.py)."""

from __future__ import annotations

import io

from hypothesis import example, given
from hypothesis import strategies as st

from hostd.protocol import jobcheck
from hostd.protocol.jobcheck import MAX_FINDINGS, Findings, check_program
from hostd.protocol.program import program_lines


def check(
    text: str, dialect: str = "grbl", limit: int = 127, policy: str | None = None
) -> Findings:
    lines = program_lines(io.StringIO(text))
    return check_program(lines, dialect=dialect, max_line_bytes=limit, tool_change=policy)


def test_a_clean_program_has_no_findings() -> None:
    assert not check("G21 G90\nG0 X1 Y1 (a long comment " + "x" * 300 + ")\nG1 X2 F100\nM5\n")


def test_the_check_counts_the_sendable_lines_it_read() -> None:
    """The job's total (job.start takes it from here): comments, blanks and tape marks
    are not lines the board gets; lines with findings are."""
    too_long = "G1 X1" + " Y1" * 50
    found = check(f"%\n(setup)\nG21 G90\n\n  ; a comment\nG1 X1 F100\n{too_long}\nM5\n%\n")
    assert found.lines == 4
    assert [f.line for f in found.found] == [7]
    assert check("").lines == 0


def test_a_line_longer_than_grbls_buffer_counts_its_n_word() -> None:
    # 125 bytes of G-code and the LF fit 127; with `N3 ` in front they do not.
    line = "G1 X1" + " Y1" * 40
    found = check(f"G21\nG90\n{line}\n")
    assert [(f.line, f.kind) for f in found.found] == [(3, "unsendable")]
    assert "receive buffer" in found.found[0].text
    assert not check(f"G21\nG90\n{line}\n", limit=255)  # grblHAL's 1024 byte buffer, say


def test_m6_needs_a_tool_change_policy() -> None:
    found = check("G21\nT1 M06\n", dialect="g2core", limit=512)
    assert [(f.line, f.kind) for f in found.found] == [(2, "tool-change")]
    assert not check("G21\nT1 M06\n", dialect="g2core", limit=512, policy="pause")
    assert check("T1 M6\n", dialect="g2core", limit=512, policy="refuse")


def test_a_held_tool_change_must_name_its_tool() -> None:
    """Under "pause" and "probe" the operator is told which tool: a T word must say."""
    found = check("G21\nM6\nT2\nM6\n", dialect="g2core", limit=512, policy="pause")
    assert [(f.line, f.kind) for f in found.found] == [(2, "tool-change")]
    assert "T word" in found.found[0].text
    assert not check("T3\nG0 X1\nM6\n", policy="pause")  # the T word before it counts
    assert not check("T3\nG0 X1\nM6\n", policy="probe")
    assert check("G0 X1\nM6\n", policy="probe")


def test_ignore_notes_each_m6_it_strips() -> None:
    found = check("G21\nT1 M6\nG0 X1\nM06 T2\n", policy="ignore")
    assert not found  # nothing refuses the file
    assert [(n.line, n.kind) for n in found.notes] == [
        (2, "tool-change-ignored"),
        (4, "tool-change-ignored"),
    ]
    assert "T2" in found.notes[1].text and found.notes_total == 2


def test_codes_the_dialect_lacks_are_named_with_their_line() -> None:
    found = check("G21\nG0 X1\nG43 H1\nG38.2 Z-5 F10\nG81 X1 Y1 Z-1 R1\n")
    assert [(f.line, f.text) for f in found.found] == [
        (3, "G43 is not supported by grbl"),
        (5, "G81 is not supported by grbl"),
    ]


def test_findings_are_bounded_and_counted() -> None:
    found = check("G43 H1\n" * (MAX_FINDINGS + 25))
    assert len(found.found) == MAX_FINDINGS and found.total == MAX_FINDINGS + 25
    assert "and 70 more" in found.summary()


def test_numbers_no_board_reads_are_refused_with_their_line() -> None:
    text = "G21\nG1 X1 F" + "9" * 400 + "\nG1 Xnan\nG1 X2 (F" + "9" * 40 + ")\n"
    found = check(text, dialect="g2core", limit=512)
    # g2core's own encoder already refuses the 400 digits; the check names the rest.
    assert [(f.line, f.kind) for f in found.found] == [(2, "unsendable"), (3, "number")]
    assert "integer digits" in found.found[0].text and "nan" in found.found[1].text
    assert [f.kind for f in check("G1 Finf\n").found] == ["number"]  # grbl's encoder sends it


# Texts made of what the two readings look at: digits, letters that spell inf and nan
# in either case, signs, points, blanks and comments.
_MISSPELLINGS = st.text(alphabet="0123456789XxFfIiNnAa+-. \t();", max_size=40)


@given(_MISSPELLINGS)
@example("Xinf")
@example("F -NaN")
@example("X1234567890")
@example("X12345(a)67890")
@example("(inf) X1")
def test_the_quick_look_at_a_lines_numbers_misses_nothing(text: str) -> None:
    """Most lines are passed by `may_misspell_a_number` without their words read: for
    every text, the finding is the one the full reading gives."""
    assert jobcheck._bad_number(text) == jobcheck._read_bad_number(text)
