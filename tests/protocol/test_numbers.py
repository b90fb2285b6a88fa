"""The one way the host writes a number for the board: finite, bounded, fixed decimals."""

from __future__ import annotations

import math
import re

import pytest
from hypothesis import given
from hypothesis import strategies as st

from hostd.protocol.numbers import (
    MAX_DISTANCE,
    MAX_FEED,
    format_distance,
    format_feed,
    format_setting,
)
from hostd.protocol.refusals import InvalidCommand, Refusal
from tests.fuzz.strategies import fuzz

PLAIN = re.compile(r"-?[0-9]+\.[0-9]+")


def test_distances_have_four_decimals_feeds_three() -> None:
    assert format_distance(1.5) == "1.5000"
    assert format_distance(-0.00004) == "0.0000"  # never -0
    assert format_distance(MAX_DISTANCE) == "100000.0000"
    assert format_feed(600) == "600.000"
    assert format_feed(0.001) == "0.001"


def test_settings_keep_integers_and_round_floats_to_six_decimals() -> None:
    assert format_setting(16000, "xvm") == "16000"
    assert format_setting(1.8, "1sa") == "1.8"
    assert format_setting(1e-7, "x") == "0.0"
    assert format_setting(2.0, "x") == "2.0"
    assert format_setting(-999_999_999, "x") == "-999999999"


@pytest.mark.parametrize(
    "value", [math.inf, -math.inf, math.nan, 1e300, 100000.00005 + 0.0001, 10**400]
)
def test_a_distance_out_of_bounds_is_refused(value: float) -> None:
    with pytest.raises(InvalidCommand) as err:
        format_distance(value)
    assert err.value.refusal is Refusal.BAD_NUMBER


@pytest.mark.parametrize("value", [0, -1, 0.0004, 1e300, math.inf, math.nan, MAX_FEED + 1])
def test_a_feed_out_of_bounds_is_refused(value: float) -> None:
    with pytest.raises(InvalidCommand):
        format_feed(value)


@pytest.mark.parametrize("value", [10**9, -(10**9), 1e9, 1e300, math.inf, math.nan, True])
def test_a_setting_out_of_bounds_is_refused(value: float) -> None:
    with pytest.raises(InvalidCommand):
        format_setting(value, "xvm")


def test_huge_integers_are_not_printed_in_full_in_the_message() -> None:
    with pytest.raises(InvalidCommand) as err:
        format_setting(10**400, "xvm")
    assert len(err.value.message) < 200


@fuzz(500)
@given(st.floats(allow_nan=True, allow_infinity=True) | st.integers())
def test_any_number_is_written_plainly_within_bounds_or_refused(value: float) -> None:
    try:
        text = format_distance(value)
    except InvalidCommand as err:
        assert err.refusal is Refusal.BAD_NUMBER
        assert not (math.isfinite(value) and abs(value) < MAX_DISTANCE - 1e-4)
        return
    assert PLAIN.fullmatch(text) and len(text.partition(".")[2]) == 4
    assert abs(float(text)) <= MAX_DISTANCE
    assert abs(float(text) - value) <= 0.00005 + 1e-9


@fuzz(500)
@given(st.floats(allow_nan=True, allow_infinity=True) | st.integers())
def test_any_setting_number_is_plain_or_refused(value: float) -> None:
    try:
        text = format_setting(value, "x")
    except InvalidCommand:
        return
    assert "e" not in text.lower() and "inf" not in text and "nan" not in text
    assert abs(float(text)) < 1e9
