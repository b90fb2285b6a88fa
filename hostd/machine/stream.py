"""A job's file on its way into the session, and the job's outcome as its runner awaits it.

The session holds the job's read position (hostd/protocol/stream.py): what
is sent, answered, executed, and how the job ended. This side holds what
the session must not: the file (an iterator of its lines, read no faster
than the board takes them, but for the look-ahead fed in blocks), and the
asyncio objects the runner waits on. The engine calls `fill` after every
step it delivers, and `ended` when the session tells `StreamEnded`.

`holds`, if given, names file lines the job holds before (a tool change's
M6, hostd/machine/toolchange.py): each is fed as the session's hold point,
and `reached` is set once the session holds there.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Container, Iterator, Sequence
from itertools import islice

from hostd.protocol.stream import LOOK_AHEAD, Stream
from hostd.protocol.vocabulary import StreamEnd, StreamResult

__all__ = ["JobStream", "StreamEnd", "StreamResult"]


class JobStream:
    """A job's source of lines, the session's position in it, and its outcome."""

    def __init__(
        self,
        lines: Iterator[tuple[int, str]],
        job_id: int | None = None,
        *,
        numbered: bool = False,
        holds: Container[int] | None = None,
        look_ahead: int = LOOK_AHEAD,
    ) -> None:
        self._lines = lines
        self._look_ahead = look_ahead
        self._holds = holds
        self.job_id = job_id
        self.numbered = numbered
        # The session's, from `start` on: the counts are read from it.
        self.position = Stream(job_id, numbered=numbered)
        self.result: asyncio.Future[StreamResult] = asyncio.get_running_loop().create_future()
        # Set when `acked` reaches `wake_at`, and when the stream ends: its runner's cue.
        self.wake = asyncio.Event()
        self.wake_at: int | None = None
        # Set when the session holds at one of `holds` (cleared by whoever waits for it).
        self.reached = asyncio.Event()

    def start(
        self,
        encode: Callable[[str, int | None], bytes],
        encode_block: Callable[[Sequence[int], Sequence[str]], list[bytes] | None] | None = None,
    ) -> Stream:
        """The session's position in this job, its lines encoded in the session's dialect."""
        self.position = Stream(
            self.job_id,
            encode,
            numbered=self.numbered,
            encode_block=encode_block,
            look_ahead=self._look_ahead,
        )
        return self.position

    def fill(self) -> bool:
        """Feed the session the lines it wants next; True if it had room and nothing ahead
        (it must be pumped again now), or the file just ended (it may be complete)."""
        position = self.position
        want = position.wanted()
        if want <= 0:
            return False
        again = position.starved
        lines = self._lines
        holds = self._holds
        if holds is None:  # no hold point: the lines go in as one batch
            batch = list(islice(lines, want))
            position.feed_many(batch)
            if len(batch) < want:
                position.end_of_input()
                return True
            return again
        for _ in range(want):
            item = next(lines, None)
            if item is None:
                position.end_of_input()
                return True
            if holds is not None and item[0] in holds:
                position.feed(item[0], item[1], hold=True)
            else:
                position.feed(item[0], item[1])
        return again

    def stepped(self) -> None:
        """After a step: wake the runner if the answered lines crossed its mark, and
        whoever waits for a hold point if the session holds at one."""
        if self.position.held is not None and not self.reached.is_set():
            self.reached.set()
        wake_at = self.wake_at
        if wake_at is not None and self.position.acked >= wake_at:
            self.wake_at = None
            self.wake.set()

    def waits_at(self, line: int) -> None:
        """The job waits at its hold point `line`, the board having run every line before
        it and come to rest (toolchange.py checks both): the job's place, its
        `line_executed`, is that line, the next to run, and a resume starts there. The
        line the board last reported is finished: run again, it may start from where
        no position is known (line 2 of `G21` then `G0 X0 Y0 Z0`), and job.recovery
        would find no safe approach."""
        position = self.position
        position.line_executed = max(line, position.line_executed or 0)

    def ended(self, result: StreamResult) -> None:
        """The session told the end: resolve the outcome, wake the runner."""
        if not self.result.done():
            self.result.set_result(result)
        self.wake.set()

    # -- the counts, as the session keeps them ------------------------------------

    @property
    def held(self) -> int | None:
        """The file line the job holds before, once its turn came; else None."""
        return self.position.held

    @property
    def paused(self) -> bool:
        """The user's pause (`!` to `~`), apart from any hold."""
        return self.position.paused

    @property
    def done(self) -> bool:
        return self.position.done

    @property
    def sent(self) -> int:
        return self.position.sent

    @property
    def acked(self) -> int:
        return self.position.acked

    @property
    def rejected(self) -> int:
        return self.position.rejected

    @property
    def discarded(self) -> int:
        return self.position.discarded

    @property
    def line_executed(self) -> int | None:
        return self.position.line_executed

    @property
    def last_acked_line(self) -> int | None:
        return self.position.last_acked_line
