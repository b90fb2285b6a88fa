"""`Tally`: a warning that a flood repeats is logged at most once an interval, and every
repeat is counted in a record: none is lost, none costs a line of its own."""

from __future__ import annotations

import asyncio
from collections.abc import MutableMapping
from typing import Any

import pytest
import structlog
from structlog.testing import capture_logs

from hostd.api.tally import Tally

pytestmark = pytest.mark.asyncio

log = structlog.get_logger("tests")


def told(records: list[MutableMapping[str, Any]], event: str) -> int:
    """How many warnings the records of `event` stand for."""
    return sum(int(r.get("repeats", 1)) for r in records if r["event"] == event)


async def test_a_burst_is_one_record_in_full_and_one_with_how_many_more() -> None:
    now = [10.0]
    with capture_logs() as records:
        tally = Tally(log, "refused", interval=1.0, clock=lambda: now[0])
        for i in range(1000):
            tally.warning(reason=f"flood {i}")
        assert [r["reason"] for r in records] == ["flood 0"]  # the first, at once
        tally.flush()
    assert len(records) == 2
    assert records[1]["repeats"] == 999 and records[1]["reason"] == "flood 999"  # the last's
    assert told(records, "refused") == tally.count == 1000


async def test_the_repeats_are_told_when_the_interval_ends_without_being_asked() -> None:
    with capture_logs() as records:
        tally = Tally(log, "refused", interval=0.05)
        for _ in range(50):
            tally.warning(code=1)
        async with asyncio.timeout(5):
            while len(records) < 2:  # noqa: ASYNC110 (the timer's record is what is awaited)
                await asyncio.sleep(0.01)
    assert records[1]["repeats"] == 49 and told(records, "refused") == 50


async def test_a_lasting_flood_is_a_record_an_interval_and_a_lone_one_later_is_in_full() -> None:
    now = [0.0]
    with capture_logs() as records:
        tally = Tally(log, "refused", interval=1.0, clock=lambda: now[0])
        for step in range(500):  # five seconds of a hundred a second
            now[0] = step / 100
            tally.warning()
            if step % 100 == 99:
                tally.flush()  # the interval's timer, at its time
        assert len(records) <= 6
        assert told(records, "refused") == 500
        now[0] = 60.0
        tally.warning(reason="alone")  # long after: not a flood, told in full at once
        assert records[-1] == {"event": "refused", "reason": "alone", "log_level": "warning"}
        tally.flush()  # nothing pending: nothing more
    assert told(records, "refused") == 501 and len(records) <= 7


async def test_each_record_goes_to_the_logger_it_was_given() -> None:
    with capture_logs() as records:
        tally = Tally(log, "refused", interval=1.0, clock=lambda: 0.0)
        tally.warning(log.bind(caller="a"))
        tally.warning(log.bind(caller="b"))
        tally.flush()
    assert [(r["caller"], r.get("repeats", 1)) for r in records] == [("a", 1), ("b", 1)]
