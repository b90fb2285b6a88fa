"""One timer for every resting link of an event loop: the reads pacing put off, taken together.

The engine's pacing (docs/protocol.md, "Reading at the pace of the motion")
asks a link to read nothing for a moment while its board answers at the pace
of its motion, so that one read takes several answers. What a line costs a
small computer is mostly the wake-up that reads it (docs/performance.md), and
a timer of its own per link is a wake-up of its own per link: four lasers
rastering would wake the daemon four times where one wake-up can read all
four. (The first pacing, 71392a9, had a timer a link, and cost more than it
saved.)

So the links of one event loop share one `ReadPacer`. It keeps when each
resting link is due, and one timer, at the earliest. When the timer fires it
ends the rest of every link due by then or within `SLACK` after (read a little
early, never late), so their reads are one wake-up, and sets the timer again
for the next link due, if any.
"""

from __future__ import annotations

import asyncio
import math
import weakref
from typing import Protocol

SLACK = 0.001  # seconds: a rest due this soon after the timer ends with it


class Resting(Protocol):
    """A link resting its reading."""

    def end_rest(self) -> None: ...


class ReadPacer:
    """The resting links of one event loop, and the one timer that ends their rests."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        # Weak: the loop keys the pacer in `_pacers`, which must not keep it alive.
        self._loop = weakref.ref(loop)
        self._due: dict[Resting, float] = {}  # loop time each rest ends
        self._timer: asyncio.TimerHandle | None = None
        self._timer_at = math.inf

    def rest(self, who: Resting, seconds: float) -> None:
        """`who` reads nothing until `seconds` from now (or a little before: `SLACK`).

        Called from the loop's thread, as every link's call is.
        """
        loop = self._loop()
        assert loop is not None  # a link rests only while its loop runs
        at = loop.time() + seconds
        self._due[who] = at
        if at < self._timer_at:
            self._arm(loop, at)

    def cancel(self, who: Resting) -> None:
        """`who` stops resting without being told (it is closing)."""
        self._due.pop(who, None)
        if not self._due and self._timer is not None:
            self._timer.cancel()
            self._timer, self._timer_at = None, math.inf

    @property
    def resting(self) -> int:
        """Links resting now."""
        return len(self._due)

    def _arm(self, loop: asyncio.AbstractEventLoop, at: float) -> None:
        if self._timer is not None:
            self._timer.cancel()
        self._timer_at = at
        self._timer = loop.call_at(at, self._fire, loop)

    def _fire(self, loop: asyncio.AbstractEventLoop) -> None:
        # From the time the timer was set for: uvloop fires up to half a millisecond
        # before it (its timers count whole milliseconds), and the rests due just after
        # the earliest must still end with it.
        horizon = max(loop.time(), self._timer_at) + SLACK
        self._timer, self._timer_at = None, math.inf
        due = [who for who, at in self._due.items() if at <= horizon]
        for who in due:
            del self._due[who]
        if self._due:
            self._arm(loop, min(self._due.values()))
        for who in due:
            who.end_rest()


_pacers: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, ReadPacer] = (
    weakref.WeakKeyDictionary()
)


def pacer() -> ReadPacer:
    """The running loop's pacer (one a loop: a test's loop has its own). A link asks once,
    when it opens: `asyncio.get_running_loop` costs a `getpid` system call a call."""
    loop = asyncio.get_running_loop()
    found = _pacers.get(loop)
    if found is None:
        found = _pacers[loop] = ReadPacer(loop)
    return found
