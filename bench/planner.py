"""A board's motion planner as the bench's controllers model it: N blocks, drained at a fixed rate.

Why a model: the bench's question on a small computer (P8) is not how fast
the host can go but whether a board rastering at 1,000-2,000 short lines a
second ever runs out of moves because the host was late. A real board
answers a line when the line enters its planner (grbl: `ok` after
`plan_buffer_line`, motion_control.c `mc_line` waits for a free block;
g2core: a data line is read only while the planner has room, controller.cpp,
so its `{r}` waits too), and the planner runs its blocks one after another.

Event times, not a timer per block: line k, read at `arrival`, enters the
planner when a block is free, `entry = max(arrival, done[k - blocks])`; it
starts when the block before it is done, and takes `period` seconds. If it
enters after the block before it was done, the planner ran empty in between:
a starvation of `entry - done[k - 1]` seconds, recorded when it happens
between a job's first and last lines. Computing with the times the events
would have had on a board keeps the controller process's own lateness (it
is a Python process on a shared CPU) out of the answer's time it models,
except for `arrival`, which is when the controller read the line: a
controller that reads late makes the host look later than it was, never
earlier. The one exception the controller can prove: a read's first line,
when the port's input alone woke the process and it then waited for a CPU,
arrived at the wake-up (instant_controller.py `woken_at`), not at the read.

Holds stop the clock: a board in a feedhold runs no block, so time spent
held is taken out (`hold`/`resume`) and the planner's times are on a clock
that stands still while held.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field


@dataclass
class Starvation:
    at: float  # when the planner ran empty (time.monotonic())
    seconds: float  # how long it stayed empty


@dataclass
class Planner:
    blocks: int  # lines the planner holds
    period: float  # seconds a block takes to run
    done: deque[float] = field(default_factory=deque)  # run-clock end times, in order
    held_total: float = 0.0  # seconds held, over the whole life
    held_since: float | None = None
    starved: list[Starvation] = field(default_factory=list)
    in_job: bool = False  # between a job's first and last lines: an empty planner is starving
    last_done: float = 0.0  # run-clock time the last block planned is done
    # The last `blocks` blocks' end times, never dropped by the clock: block k waits
    # for block k - blocks, even when the controller only gets round to it later.
    recent: deque[float] = field(default_factory=deque)

    def clock(self, now: float) -> float:
        """The run clock: monotonic time with the time held taken out."""
        if self.held_since is not None:
            return self.held_since - self.held_total
        return now - self.held_total

    def to_wall(self, run: float) -> float:
        return run + self.held_total

    def hold(self, now: float) -> None:
        if self.held_since is None:
            self.held_since = now

    def resume(self, now: float) -> None:
        if self.held_since is not None:
            self.held_total += now - self.held_since
            self.held_since = None

    def _drop_done(self, run_now: float) -> None:
        while self.done and self.done[0] <= run_now:
            self.done.popleft()

    def free_at(self, now: float) -> float | None:
        """Run-clock time a block frees (None: one is free now)."""
        self._drop_done(self.clock(now))
        return self.done[0] if len(self.done) >= self.blocks else None

    def queued(self, now: float) -> int:
        self._drop_done(self.clock(now))
        return len(self.done)

    def busy(self, now: float) -> bool:
        return self.queued(now) > 0

    def next_free_wall(self, now: float) -> float | None:
        """Monotonic time the next block frees, if the planner is full and not held."""
        run = self.free_at(now)
        if run is None or self.held_since is not None:
            return None
        return self.to_wall(run)

    def add(self, arrival: float, now: float) -> None:
        """Plan a block that arrived (was read) at `arrival`; the caller checked for room.

        It entered the planner at the later of its arrival and the moment a block
        freed (which may be before `now`: the controller process woke late).
        """
        run_arrival = self.clock(arrival) if self.held_since is None else self.clock(now)
        entry = run_arrival
        if len(self.recent) >= self.blocks:
            entry = max(entry, self.recent[0])
        if self.in_job and entry > self.last_done:
            self.starved.append(Starvation(self.to_wall(self.last_done), entry - self.last_done))
        start = max(entry, self.last_done)
        self.last_done = start + self.period
        self.done.append(self.last_done)
        self.recent.append(self.last_done)
        if len(self.recent) > self.blocks:
            self.recent.popleft()

    def begin_job(self) -> None:
        self.in_job = True

    def end_job(self) -> None:
        self.in_job = False
