"""`Tally`: the API's refusals that a flood repeats, logged at most once an interval, each
one counted (docs/operations.md, "Logs")."""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable
from typing import Any


class Tally:
    """A warning a flood would repeat: logged in full at most once an `interval`, the
    repeats in between counted and told in one record at the interval's end.

    A hostile peer can make the daemon refuse thousands of things a second (MQTT
    commands past the rate limit, connections past the cap). One record each
    would cost the event loop more than the refusals themselves (a console
    line is tens of microseconds to format and write) and bury the journal.
    Nothing goes untold: the first of a burst is logged with all its fields,
    and `<event>` again with `repeats=N` and the last one's fields says how
    many more came within the interval. The clock and the timer are the event
    loop's; `flush` tells what is pending at once (at a shutdown).
    """

    def __init__(
        self,
        logger: Any,
        event: str,
        interval: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._logger = logger
        self.event = event
        self.interval = interval
        self._clock = clock
        self._logged_at = -math.inf
        self._repeats = 0
        self._last: dict[str, Any] = {}
        self._timer: asyncio.TimerHandle | None = None
        self.count = 0  # every one, logged or tallied

    def warning(self, logger: Any = None, **fields: Any) -> None:
        """One more: logged now if the interval since the last record is over, else tallied."""
        self.count += 1
        now = self._clock()
        if now - self._logged_at >= self.interval and not self._repeats:
            self._logged_at = now
            (logger or self._logger).warning(self.event, **fields)
            return
        self._repeats += 1
        self._last = {"logger": logger, **fields}
        if self._timer is None:
            delay = max(0.0, self._logged_at + self.interval - now)
            self._timer = asyncio.get_running_loop().call_later(delay, self.flush)

    def flush(self) -> None:
        """Tell the repeats tallied since the last record, if any."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if not self._repeats:
            return
        fields = dict(self._last)
        logger = fields.pop("logger") or self._logger
        logger.warning(self.event, repeats=self._repeats, **fields)
        self._repeats, self._last, self._logged_at = 0, {}, self._clock()
