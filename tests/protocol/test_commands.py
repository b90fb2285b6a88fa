"""What the host may send, and the exact bytes it sends."""

from __future__ import annotations

import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from hostd.protocol.commands import (
    MAX_LINE_BYTES,
    InvalidCommand,
    Realtime,
    Refusal,
    encode_clear,
    encode_get,
    encode_in_hold,
    encode_line,
    encode_realtime,
    encode_set,
    validate_line,
)
from hostd.protocol.relaxed import parse_relaxed


def test_gcode_line_is_sent_as_is_with_one_lf() -> None:
    assert encode_line("G1 X10 Y20 F3000") == b"G1 X10 Y20 F3000\n"


_WORDISH = st.text(alphabet="GMXYZFNHhE$?{}()!%;. \t-+0123456789\x00\x18é", max_size=40)


@given(st.one_of(_WORDISH, st.text(max_size=40), st.text(min_size=500, max_size=520)))
@example("h")
@example("G1 X1.5 ")
@example("G1 X" + "1" * 10)
@example("G1 X1" + " " * 520)
def test_the_plain_line_shortcut_encodes_as_the_full_rules_do(text: str) -> None:
    """encode_line takes plain G-code in one match: it must agree with every rule."""
    try:
        expected: bytes | InvalidCommand = validate_line(text).encode("utf-8") + b"\n"
    except InvalidCommand as exc:
        expected = exc
    if isinstance(expected, InvalidCommand):
        with pytest.raises(InvalidCommand):
            encode_line(text)
    else:
        assert encode_line(text) == expected


def test_get_uses_null_the_boards_get_form() -> None:
    assert encode_get("xvm") == b'{"xvm":null}\n'
    assert encode_get("posx", "posy") == b'{"posx":null,"posy":null}\n'


def test_set_is_compact_json() -> None:
    assert encode_set({"xvm": 16000}) == b'{"xvm":16000}\n'
    assert encode_set({"sr": {"posx": True, "stat": True}}) == b'{"sr":{"posx":true,"stat":true}}\n'


def test_clear_is_sent_in_get_form() -> None:
    # The SET form ({clear:1}) is rejected by the board while alarmed.
    assert encode_clear() == b'{"clear":null}\n'


def test_in_hold_commands_are_wrapped_in_gc2() -> None:
    assert encode_in_hold("G91 G0 Z5") == b'{"gc2":"G91 G0 Z5"}\n'
    assert encode_in_hold(" M3 S1000 (say hi)\t") == b'{"gc2":"M3 S1000 (say hi)"}\n'
    assert encode_in_hold("G0\tX1") == b'{"gc2":"G0 X1"}\n'  # the board reads a TAB as a space


@pytest.mark.parametrize("line", ['M3 S1000 (say "hi")', "G0 X1 (a\\b)"])
def test_a_line_the_boards_string_cannot_hold_is_not_wrapped(line: str) -> None:
    # The board's strings have no escapes: `\"` would end the string early.
    validate_line(line)
    with pytest.raises(InvalidCommand) as err:
        encode_in_hold(line)
    assert err.value.refusal is Refusal.UNREADABLE


@pytest.mark.parametrize("command", list(Realtime))
def test_realtime_characters_are_one_byte_and_a_terminator(command: Realtime) -> None:
    assert encode_realtime(command) == command.value + b"\n"
    assert len(command.value) == 1


def test_realtime_bytes_are_the_boards() -> None:
    assert [r.value for r in Realtime] == [b"!", b"~", b"%", b"\x04", b"\x18", b"\x05"]


@pytest.mark.parametrize(
    ("line", "refusal"),
    [
        ("G1 X1\x00", Refusal.NUL),
        ("G1 X" + "1" * MAX_LINE_BYTES, Refusal.TOO_LONG),
        ("G1 X1\nG1 X2", Refusal.LINE_BREAK),
        ("G1 X1\r", Refusal.LINE_BREAK),
        ("G1\x07 X1", Refusal.CONTROL_CHAR),
        ("", Refusal.EMPTY),
        ("   ", Refusal.EMPTY),
        ("%", Refusal.TAPE_MARK),
        ("!", Refusal.REALTIME),
        ("~", Refusal.REALTIME),
        ("\x18", Refusal.REALTIME),
        ("\x04", Refusal.REALTIME),
        ("$$", Refusal.UBER_GROUP),
        ("{m:n}", Refusal.UBER_GROUP),
        ("{q:n}", Refusal.UBER_GROUP),
        ("{o:n}", Refusal.UBER_GROUP),
        ('{"m":null}', Refusal.UBER_GROUP),
        ("{Q:N}", Refusal.UBER_GROUP),
        ("H", Refusal.HELP),
        ("$h", Refusal.HELP),
        ("{flash:t}", Refusal.BOOTLOADER),
        ("$boot=1", Refusal.BOOTLOADER),
    ],
)
def test_lines_that_must_never_reach_the_board_are_refused(line: str, refusal: Refusal) -> None:
    with pytest.raises(InvalidCommand) as err:
        validate_line(line)
    assert err.value.refusal is refusal
    assert err.value.message  # a human sentence for the client


def test_longest_line_the_board_takes_is_accepted() -> None:
    line = "G1 X1 (" + "c" * (MAX_LINE_BYTES - 8) + ")"
    assert len(line) == MAX_LINE_BYTES
    assert encode_line(line).endswith(b"\n")


def test_multibyte_characters_count_as_bytes() -> None:
    with pytest.raises(InvalidCommand):
        validate_line("(" + "é" * 256 + ")")


def test_wrapping_cannot_smuggle_an_overlong_line() -> None:
    with pytest.raises(InvalidCommand) as err:
        encode_in_hold("G1 X1 (" + "c" * 496 + ")")  # the wrapping takes it past the limit
    assert err.value.refusal is Refusal.TOO_LONG


def test_single_group_queries_are_allowed() -> None:
    assert validate_line("{m1:n}") == "{m1:n}"
    assert validate_line("{x:n}") == "{x:n}"
    assert validate_line("$xvm") == "$xvm"


def test_relaxed_json_reads_as_the_board_reads_it() -> None:
    assert parse_relaxed("{xvm:n}") == {"xvm": None}
    assert parse_relaxed("{clear:n}") == {"clear": None}
    assert parse_relaxed('{"clr":null}') == {"clr": None}
    assert parse_relaxed("{sr:{posx:t,stat:t}}") == {"sr": {"posx": True, "stat": True}}
    assert parse_relaxed("{XVM:16000}") == {"xvm": 16000}
    assert parse_relaxed('{gc:"G0 X1"}') == {"gc": "G0 X1"}
    assert parse_relaxed("{xvm:banana}") is None
    assert parse_relaxed("{xvm:") is None
    assert parse_relaxed("[1,2]") is None
