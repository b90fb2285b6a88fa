"""When a job's follower looks again: at the first of its tell, its write mark and its
write, never later, never in a loop (`jobrunner.next_look`)."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from hostd.machine.jobrunner import (
    PERSIST_EVERY,
    PERSIST_GAP,
    PUBLISH_EVERY,
    WAKE_SLACK,
    next_look,
)

# Seconds before "now" that something happened: in the last few seconds, or long ago.
_AGO = st.floats(min_value=0.0, max_value=5.0, allow_nan=False)


def test_it_looks_when_the_next_tell_is_due() -> None:
    # Written 0.5 s ago (its gap over, its second not up), told 0.1 s ago: the tell is next.
    assert next_look(9.9, 9.5, 10.0) == pytest.approx(PUBLISH_EVERY - 0.1 + WAKE_SLACK)


def test_it_looks_when_the_gap_after_a_write_ends_to_set_the_line_mark() -> None:
    # Written 0.05 s ago, told 0.1 s ago: the gap ends first (a fast job's next write
    # is 100 lines after it, which the engine's mark, set then, wakes the follower for).
    assert next_look(9.9, 9.95, 10.0) == pytest.approx(PERSIST_GAP - 0.05 + WAKE_SLACK)


def test_a_slow_job_is_written_at_its_second_not_a_tell_period_later() -> None:
    # Told just now, written 0.9 s ago: the row's PERSIST_EVERY is up in 0.1 s.
    assert next_look(10.0, 9.1, 10.0) == pytest.approx(PERSIST_EVERY - 0.9 + WAKE_SLACK)


def test_with_nothing_due_it_looks_again_after_a_tell_period_not_at_once() -> None:
    # A stalled job (a long move): every due time passed; a zero wait would spin the loop.
    assert next_look(0.0, 0.0, 100.0) == PUBLISH_EVERY + WAKE_SLACK


@given(told=_AGO, persisted=_AGO)
def test_it_never_sleeps_past_a_due_look_nor_longer_than_a_tell_period(
    told: float, persisted: float
) -> None:
    clock = 1000.0
    wait = next_look(clock - told, clock - persisted, clock)
    assert WAKE_SLACK <= wait <= PUBLISH_EVERY + WAKE_SLACK
    for due in (PUBLISH_EVERY - told, PERSIST_GAP - persisted, PERSIST_EVERY - persisted):
        if due > 0:
            assert wait <= due + WAKE_SLACK + 1e-9
