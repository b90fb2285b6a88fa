"""Relaxed JSON read exactly as the board reads it, or refused: duplicates, nesting, escapes."""

from __future__ import annotations

import pytest

from hostd.protocol.commands import InvalidCommand, Refusal, validate_line
from hostd.protocol.relaxed import board_pairs, is_get, parse_relaxed, read_relaxed


def refusal(line: str) -> Refusal:
    with pytest.raises(InvalidCommand) as err:
        validate_line(line)
    assert err.value.message
    return err.value.refusal


def test_the_forms_the_board_reads_are_read() -> None:
    assert read_relaxed("{xvm:n}") == {"xvm": None}
    assert read_relaxed('{ "xvm" : null }') == {"xvm": None}
    assert read_relaxed("{XVM:16000}") == {"xvm": 16000}
    assert read_relaxed("{xvm:-2.5e3}") == {"xvm": -2500.0}
    assert read_relaxed("{1ma:n,1sa:1.8}") == {"1ma": None, "1sa": 1.8}
    assert read_relaxed("{sr:{POSX:T,stat:true,vel:F}}") == {
        "sr": {"posx": True, "stat": True, "vel": False}
    }
    assert read_relaxed('{gc:"G0 X1 (Hi)"}') == {"gc": "G0 X1 (Hi)"}
    assert read_relaxed('{posx:""}') == {"posx": ""}


def test_pairs_keep_the_order_the_board_runs_them_in() -> None:
    assert list(read_relaxed("{zvm:1,xvm:2,yvm:3}")) == ["zvm", "xvm", "yvm"]


@pytest.mark.parametrize(
    "line",
    [
        '{"gc":"G0 X100","clear":n,"gc":n}',  # the line: it moved, then cleared
        '{gc:"G0 X1",GC:n}',  # the board lower-cases names
        "{xvm:1,Xvm:2}",
        "{sr:{posx:t,POSX:f}}",  # inside a group too
        "{xvm:1,x:{vm:2}}",  # `x:{vm}` is `xvm` on the board
        "{ej:1,sys:{ej:0}}",  # `sys` is not prefixed: its `ej` is `ej`
    ],
)
def test_a_name_given_twice_is_refused(line: str) -> None:
    assert refusal(line) is Refusal.DUPLICATE_KEY
    assert parse_relaxed(line) is None


def test_gcode_in_json_must_be_a_string() -> None:
    assert refusal("{gc:5}") is Refusal.UNREADABLE


def test_the_duplicate_message_names_the_key() -> None:
    with pytest.raises(InvalidCommand) as err:
        read_relaxed('{"gc":"G0 X100","clear":n,"gc":n}')
    assert "'gc'" in err.value.message and "in order" in err.value.message


@pytest.mark.parametrize(
    "line",
    [
        "{not json",
        "{xvm:",
        "{}",
        "{xvm:n} G0 X1",  # the board ignores what follows; the host does not guess
        "{xvm:n}{yvm:n}",
        "{x vm:n}",  # the board drops the space: `xvm`
        '{"x vm":n}',
        '{"a:b":1}',
        "{xvm:nonsense}",  # the board reads any n-word as null
        "{xvm:tree}",
        "{xvm:[1,2]}",
        "{xvm:.5}",
        "{xvm:+5}",
        "{xvm:-.5}",
        "{xvm:5.}",
        "{xvm:007}",
        "{xvm:0x10}",
        "{xvm:-inf}",
        "{xvm:nan}",
        '{xvm:"a\\"b"}',  # no escapes on the board: the string ends at the second quote
        '{xvm:"abc}',
        "{x:{vm:1},am:n}",  # the board reads `am` as `xam`
        "{x:{y:{z:1}}}",
    ],
)
def test_json_the_host_cannot_read_as_the_board_does_is_refused(line: str) -> None:
    assert refusal(line) is Refusal.UNREADABLE
    assert parse_relaxed(line) is None


@pytest.mark.parametrize("line", ["{xvm:1e300}", "{xvm:1e999}", "{xvm:1000000000}", "{xvm:-1e9}"])
def test_numbers_beyond_the_boards_limit_are_refused(line: str) -> None:
    assert refusal(line) is Refusal.BAD_NUMBER


def test_the_largest_number_the_board_reads_safely_passes() -> None:
    assert validate_line("{xvm:999999999}") == "{xvm:999999999}"
    assert validate_line("{xvm:-999999999.5}") == "{xvm:-999999999.5}"


def test_a_quoted_n_is_a_string_not_a_get() -> None:
    # The board takes `"n"` as the string n: only a bare n, null and "" are GETs.
    assert not is_get(read_relaxed('{xvm:"n"}')["xvm"])
    assert is_get(read_relaxed("{xvm:N}")["xvm"])
    assert is_get(read_relaxed('{xvm:""}')["xvm"])


def test_group_members_are_known_by_both_names() -> None:
    assert board_pairs(read_relaxed("{x:{vm:n}}")) == [
        (("x",), {"vm": None}),
        (("vm", "xvm"), None),
    ]


@pytest.mark.parametrize(
    ("line", "why"),
    [
        ("{sys:{flash:t}}", Refusal.BOOTLOADER),  # any parent: the board runs the member
        ("{xvm:{boot:1}}", Refusal.BOOTLOADER),
        ("{sys:{m:n}}", Refusal.UBER_GROUP),
        ("{help:n}", Refusal.HELP),
        ("{defa:n}", Refusal.HELP),
        ('{gc:"G0 X1e300"}', Refusal.BAD_NUMBER),  # a gc string is G-code, and checked as such
        ('{gc2:"G0 ({flash:t})"}', Refusal.ACTIVE_COMMENT),
    ],
)
def test_the_rules_apply_to_every_pair_and_to_gcode_strings(line: str, why: Refusal) -> None:
    assert refusal(line) is why


@pytest.mark.parametrize(
    "line",
    ["{jv:0}", "{ej:0}", "{sv:0}", "{si:50}", "{qv:2}", "{sr:{posx:t}}", "{se00:5}", "{defa:1}"],
)
def test_a_client_may_not_set_what_the_daemon_owns(line: str) -> None:
    assert refusal(line) is Refusal.RESERVED_KEY


def test_but_may_read_it_and_send_gcode_clears_and_alarms() -> None:
    for line in ["{jv:n}", "{sr:n}", '{"ej":""}', '{gc:"G0 X1"}', "{clear:n}", "{alarm:n}"]:
        assert validate_line(line) == line
