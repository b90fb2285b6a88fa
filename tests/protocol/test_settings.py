"""Reserved names: what settings.set and settings.get refuse, and how values are written."""

from __future__ import annotations

import pytest

from hostd.protocol.refusals import InvalidCommand, Refusal
from hostd.protocol.settings import (
    DAEMON_OWNED,
    RESERVED,
    Where,
    check_key,
    check_values,
    set_lines,
)

ISSUE_KEYS = ["gc", "ej", "jv", "sv", "si", "qv", "tv", "defa", "boot"]


@pytest.mark.parametrize(
    "key", [*ISSUE_KEYS, "gc2", "clear", "clr", "alarm", "shutd", "panic", "sr", "flash", "se07"]
)
def test_names_that_are_not_settings_are_refused_with_the_reason(key: str) -> None:
    for spelled in (key, key.upper()):
        with pytest.raises(InvalidCommand) as err:
            check_key(spelled)
        assert err.value.refusal is Refusal.RESERVED_KEY
        assert repr(key) in err.value.message and RESERVED[key].reason in err.value.message


def test_every_entry_says_why() -> None:
    assert all(r.reason and Where.SET in r.where for r in RESERVED.values())


def test_reading_is_refused_only_where_a_get_acts() -> None:
    for key in ("clear", "clr", "alarm", "shutd", "panic", "defa", "flash", "estpc", "er"):
        with pytest.raises(InvalidCommand):
            check_key(key, read=True)
    for key in ("gc", "jv", "sr", "si", "me", "xvm"):
        check_key(key, read=True)


def test_the_daemon_owns_its_link_settings_and_the_status_report_list() -> None:
    assert {"ej", "jv", "sv", "si", "qv", "tv", "sr", "defa", "se00", "se38"} <= DAEMON_OWNED
    assert not {"gc", "clear", "alarm"} & DAEMON_OWNED


def test_values_are_written_in_the_boards_forms() -> None:
    assert set_lines({"xvm": 12000, "1sa": 1.8, "ex": True, "XJM": 1e-7}) == [
        '{"xvm":12000}',
        '{"1sa":1.8}',
        '{"ex":true}',
        '{"xjm":0.0}',
    ]
    assert set_lines({"uda0": "0x1F"}) == ['{"uda0":"0x1F"}']


@pytest.mark.parametrize(
    ("values", "why"),
    [
        ({"xvm": 1e300}, Refusal.BAD_NUMBER),
        ({"xvm": float("inf")}, Refusal.BAD_NUMBER),
        ({"xvm": 10**30}, Refusal.BAD_NUMBER),
        ({"xvm": ""}, Refusal.BAD_VALUE),  # `""` is a GET on the board
        ({"xvm": "a b"}, Refusal.BAD_VALUE),  # the board drops the space
        ({"xvm": 'a"b'}, Refusal.BAD_VALUE),
        ({"xvm": "a\\b"}, Refusal.BAD_VALUE),
        ({"xvm": "a\x07"}, Refusal.BAD_VALUE),
        ({"xvm": "(a)"}, Refusal.BAD_VALUE),
        ({"xvm": "é"}, Refusal.BAD_VALUE),
        ({"xvm": "a" * 101}, Refusal.BAD_VALUE),
        ({"xvm": 1, "XVM": 2}, Refusal.DUPLICATE_KEY),
        ({"gc": "G0 X1"}, Refusal.RESERVED_KEY),
    ],
)
def test_values_the_board_would_misread_are_refused(
    values: dict[str, bool | int | float | str], why: Refusal
) -> None:
    with pytest.raises(InvalidCommand) as err:
        check_values(values)
    assert err.value.refusal is why
