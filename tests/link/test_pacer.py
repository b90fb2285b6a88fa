"""The loop's read pacer: one timer ends the rests of every link due together.

Each test waits for the rests' ends (events), never for a fixed time; the rests
are short, and what is checked is which rests end in the same timer call and
in what order, which no scheduling delay changes.
"""

from __future__ import annotations

import asyncio

import pytest

from hostd.link.pacer import SLACK, ReadPacer, pacer

pytestmark = pytest.mark.asyncio


class Rester:
    """A link's stand-in: records its rest's end, and how many others still rested then."""

    def __init__(self, name: str, ends: list[tuple[str, int]], pacer: ReadPacer) -> None:
        self.name, self.ends, self.pacer = name, ends, pacer
        self.ended = asyncio.Event()

    def end_rest(self) -> None:
        self.ends.append((self.name, self.pacer.resting))
        self.ended.set()


async def test_rests_due_within_the_slack_end_in_one_timer_call() -> None:
    """Four lasers' links resting until nearly the same moment: one wake-up reads all four."""
    readers = ReadPacer(asyncio.get_running_loop())
    ends: list[tuple[str, int]] = []
    links = [Rester(f"laser{i}", ends, readers) for i in range(4)]
    for i, link in enumerate(links):
        readers.rest(link, 0.02 + i * SLACK / 4)
    async with asyncio.timeout(5):
        await asyncio.gather(*(link.ended.wait() for link in links))
    # Each was told with none left resting: all four were taken off in the same call.
    assert ends == [(f"laser{i}", 0) for i in range(4)]


async def test_a_rest_due_past_the_slack_waits_for_its_own_time() -> None:
    readers = ReadPacer(asyncio.get_running_loop())
    ends: list[tuple[str, int]] = []
    soon, later = Rester("soon", ends, readers), Rester("later", ends, readers)
    readers.rest(later, 0.2)
    readers.rest(soon, 0.01)  # earlier than the timer set: it is set again, earlier
    async with asyncio.timeout(5):
        await soon.ended.wait()
    assert ends == [("soon", 1)]  # `later` still rests
    loop = asyncio.get_running_loop()
    began = loop.time()
    async with asyncio.timeout(5):
        await later.ended.wait()
    assert ends == [("soon", 1), ("later", 0)]
    assert loop.time() > began  # it was not ended with `soon`


async def test_a_cancelled_rest_never_ends_and_leaves_no_timer() -> None:
    readers = ReadPacer(asyncio.get_running_loop())
    ends: list[tuple[str, int]] = []
    closing, other = Rester("closing", ends, readers), Rester("other", ends, readers)
    readers.rest(closing, 0.01)
    readers.cancel(closing)
    assert readers.resting == 0 and readers._timer is None  # nothing left to wake for
    readers.rest(closing, 0.01)
    readers.rest(other, 0.01)
    readers.cancel(closing)
    async with asyncio.timeout(5):
        await other.ended.wait()
    await asyncio.sleep(0.03)  # past the cancelled rest's time: it must not end
    assert ends == [("other", 0)]
    assert not closing.ended.is_set()


async def test_each_loop_has_its_own_pacer() -> None:
    here = pacer()
    assert pacer() is here

    async def elsewhere() -> ReadPacer:
        return pacer()

    assert await asyncio.to_thread(asyncio.run, elsewhere()) is not here
