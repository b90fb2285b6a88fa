"""G-code words the board would misread are refused; ordinary G-code passes untouched."""

from __future__ import annotations

import re

import pytest
from hypothesis import given
from hypothesis import strategies as st

from hostd.protocol import gcode
from hostd.protocol.commands import InvalidCommand, Refusal, validate_line
from hostd.protocol.gcode import check_gcode, jog_line
from tests.fuzz.strategies import fuzz


def refusal(line: str) -> Refusal:
    with pytest.raises(InvalidCommand) as err:
        validate_line(line)
    assert err.value.message
    return err.value.refusal


@pytest.mark.parametrize(
    "line",
    [
        "G0 X100",
        "N12345 G1 X-0.5 Y.5 Z1. F1500",
        "M3 S12000",
        "G4 P0.5",
        "G2 X10 Y0 I5 J0",
        "g1x10y20f3000",
        "G10 L2 P1 X0 Y0",
        "G38.2 Z-10 F100",
        "T1 M6",
        "N999999999 G0 X1",
        "G0 X999999999.9999",
        "G0 X0000000000001",  # leading zeros are dropped by the board
        "G1 X1 E5",  # an E word, after a space
        "G0 X1 (a comment with 1e5 and 99999999999 in it)",
        "G0 X1 ; 1e300 after a semicolon is a comment",
        "N10 G1 X1*57",  # the checksum is not a word
    ],
)
def test_ordinary_gcode_passes(line: str) -> None:
    assert validate_line(line) == line


@pytest.mark.parametrize(
    "line",
    [
        "G0 X1e300",  # the board reads X1 and E300
        "G0 X1E5",
        "G0 X2.5e-1",
        "G0 X1.e3",
        "G0 X99999999999",  # wraps past 2^31 in the board's reader
        "G0 X3000000000",
        "G0 X1000000000",
        "N1234567890 G0 X1",
        "G0 X1 000",  # the board drops the space: X1000
        "G0 X1 (note) 000",
        "G0 X1 .5",
    ],
)
def test_numbers_the_board_would_misread_are_refused(line: str) -> None:
    assert refusal(line) is Refusal.BAD_NUMBER


@pytest.mark.parametrize(
    "line", ["G0 ({flash:t})", "({xvm:1e300})", "M100 ({sv:0})", "(msg hello)", "G0 X1 (MSG hi)"]
)
def test_active_comments_are_refused(line: str) -> None:
    # The board runs the JSON itself, past every rule the host applies to JSON lines.
    assert refusal(line) is Refusal.ACTIVE_COMMENT


def test_jog_lines_use_fixed_decimals_and_never_an_exponent() -> None:
    assert jog_line({"x": 1.5, "y": -0.5}, 600) == "G91 G1 X1.5000 Y-0.5000 F600.000"
    assert jog_line({"z": -0.00001}, 1234.56789) == "G91 G1 Z0.0000 F1234.568"
    assert jog_line({"a": 100000}, 1e6) == "G91 G1 A100000.0000 F1000000.000"


@pytest.mark.parametrize(
    ("axes", "feed"),
    [
        ({"x": 1e300}, 600),
        ({"x": float("inf")}, 600),
        ({"x": float("nan")}, 600),
        ({"x": 100000.001}, 600),
        ({"x": 1}, 1e300),
        ({"x": 1}, 0.0004),  # rounds to F0.000
        ({"x": 1}, float("inf")),
        ({"q": 1}, 600),
        ({}, 600),
    ],
)
def test_jog_values_out_of_bounds_are_refused(axes: dict[str, float], feed: float) -> None:
    with pytest.raises(InvalidCommand):
        jog_line(axes, feed)


# -- hypothesis ----------------------------------------------------------------

letters = st.sampled_from("GMXYZABCIJKFSPNTRLHDQ")
plain_numbers = st.decimals(
    min_value=-999_999_999, max_value=999_999_999, places=4, allow_nan=False
).map(lambda d: format(d, "f"))
words = st.tuples(letters, st.sampled_from(["", " "]), plain_numbers).map("".join)
comments = st.sampled_from(["", " (comment)", " (x 1e5 99999999999)", " ; 1e300"])
# A line starts with G, M or N: one starting with H is a help request, not G-code.
gcode_lines = st.tuples(
    st.sampled_from(["G1 ", "M3 ", "N10 "]), st.lists(words, max_size=8).map(" ".join), comments
).map("".join)


@fuzz(500)
@given(gcode_lines)
def test_any_word_with_nine_integer_digits_or_fewer_passes(line: str) -> None:
    assert validate_line(line) == line


@fuzz(300)
@given(letters, st.integers(min_value=10**9, max_value=10**30), st.booleans())
def test_any_number_of_ten_integer_digits_or_more_is_refused(
    letter: str, value: int, negative: bool
) -> None:
    line = f"G0 {letter}{'-' if negative else ''}{value}.5"
    assert refusal(line) is Refusal.BAD_NUMBER


@fuzz(300)
@given(
    letters,
    st.floats(allow_nan=False, allow_infinity=False).map(repr).filter(lambda t: "e" in t),
)
def test_any_number_in_exponent_notation_is_refused(letter: str, number: str) -> None:
    assert refusal(f"G1 {letter}{number}") is Refusal.BAD_NUMBER


gcodeish = st.lists(
    st.sampled_from([*"GXYZEe0123456789.-+ ;(){}*%", "msg", "1e", " E", "00"]),
    max_size=30,
).map("".join)


@fuzz(800)
@given(gcodeish)
def test_the_fast_path_never_passes_what_the_full_reading_refuses(text: str) -> None:
    # Job lines take a one-regex fast path: it must be a subset of the full rules.
    if gcode._PLAIN.fullmatch(text):
        gcode._check_words(text)


# The fast path as first written, backtracking: the possessive one must match the same.
_PLAIN_BACKTRACKING = re.compile(
    r"(?:[A-DF-Za-df-z][ \t]*(?:[-+]?[0-9]{0,9}(?:\.[0-9]*)?)?[ \t]*)+"
)


@fuzz(800)
@given(gcodeish | st.lists(st.sampled_from([*"GXx0123456789.-+ \t"]), max_size=40).map("".join))
def test_the_possessive_fast_path_matches_what_backtracking_would(text: str) -> None:
    assert bool(gcode._PLAIN.fullmatch(text)) == bool(_PLAIN_BACKTRACKING.fullmatch(text))


# Words as a job's lines hold them, plain or nearly: blanks of spaces and tabs, numbers
# within the fast path's rules and just past them.
_blank = st.sampled_from(["", " ", "\t", "  ", " \t"])
words = st.lists(
    st.tuples(
        st.sampled_from([*"GXYZFSNnEe"]),
        _blank,
        st.sampled_from(["", "1", "-2.5", "+.5", "7.", "123456789", "1234567890", "1.2.3", "--1"]),
        _blank,
    ).map("".join),
    min_size=1,
    max_size=5,
).map("".join)


@fuzz(800)
@given(
    st.lists(
        st.tuples(
            st.integers(min_value=0, max_value=10**8),
            gcodeish | words,
        ),
        min_size=1,
        max_size=8,
    )
)
def test_a_numbered_block_is_plain_exactly_when_each_of_its_lines_is(
    lines: list[tuple[int, str]],
) -> None:
    """A job's block in one match (one pattern for a block with a tab, a faster one for a
    block without): what `_PLAIN` says of each line, none of them an N word of its own."""
    block = "".join(f"N{number} {text}\n" for number, text in lines)
    each = all(text[:1] not in ("N", "n") and gcode._PLAIN.fullmatch(text) for _, text in lines)
    assert bool(gcode.plain_numbered_block(block)) == each


@fuzz(800)
@given(gcodeish)
def test_gcode_is_checked_or_refused_never_crashes(text: str) -> None:
    try:
        check_gcode(text)
    except InvalidCommand as err:
        assert err.refusal in (Refusal.BAD_NUMBER, Refusal.ACTIVE_COMMENT)
