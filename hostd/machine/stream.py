"""A job's lines on their way to the board, and how the job ended.

The engine pulls lines with `peek`/`take` only when the window has room, so
the source (a file, streamed) is read no faster than the board takes it, but
for LOOK_AHEAD lines: after each write the engine has the next lines read and
encoded (`prefetch`), so that the path from an answer to the next line written
carries no file reading and no encoding. A line that may not be sent is
refused when its turn comes, not when it is read ahead.
Counts only move forward: `sent` when a line is written, `acked` when the
board answers it with status 0. Every sent line ends in exactly one of
`acked`, `rejected`, `discarded`, or is still unanswered when the link is
lost. The outcome is set once.

`line_executed` is the file line the board said it was executing (its N word in
a status report; the session decides which reports say so, per dialect). It
only moves forward and never past the last line sent: every value it takes is
a lower bound of the truth, so it never claims more than the board ran.
"""

from __future__ import annotations

import asyncio
import re
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from hostd.protocol.commands import InvalidCommand, encode_line
from hostd.protocol.linemode import InFlight
from hostd.protocol.vocabulary import StreamEnd

_ACKED_KEPT = 512  # answered lines remembered: more than any planner holds blocks
LOOK_AHEAD = 8  # lines read and encoded ahead of the flow control's room
_PROGRAM_PAUSE = re.compile(rb"(?<![0-9.])[mM]0*(?:0|1|60)(?![0-9.])")


@dataclass(frozen=True, slots=True)
class StreamResult:
    end: StreamEnd
    code: int | None = None
    message: str | None = None


class JobStream:
    """A job's lines for the session (a `hostd.protocol.vocabulary.LineSource`), and its outcome."""

    def __init__(
        self,
        lines: Iterator[tuple[int, str]],
        job_id: int | None = None,
        encode: Callable[[str, int | None], bytes] | None = None,
        *,
        numbered: bool = False,
    ) -> None:
        self._lines = lines
        # The dialect's: what a job line becomes on the wire; `numbered` gives each line its
        # file line number as an N word, so that status reports say which line runs.
        self._encode = encode or (lambda text, _number: encode_line(text))
        self.numbered = numbered
        self.job_id = job_id  # the job row it belongs to, for the logs
        self._next: InFlight | None = None
        # Read ahead: a line as the flow control books it, or why it may not be sent.
        self._ahead: deque[InFlight | tuple[int, InvalidCommand]] = deque()
        self._source_done = False
        self.exhausted = False  # every line was handed out (none left ahead either)
        self.sent = 0
        self.acked = 0  # answered with status 0
        self.rejected = 0  # answered with a non-zero status
        self.discarded = 0  # dropped unanswered by the board's flush or kill
        self.last_acked_line: int | None = None
        self.line_executed: int | None = None
        self._sent_line = 0  # the highest file line number written
        self._first_line: int | None = None  # the first one (a resume's preamble is line 0)
        self._acked_lines: deque[int | None] = deque(maxlen=_ACKED_KEPT)
        # An M0/M1/M60 went out: the board stopping now is the program's pause, not an underflow.
        self.program_pause_sent = False
        self.paused = False  # from the job's `!` to its `~`: none of its lines is written
        self.result: asyncio.Future[StreamResult] = asyncio.get_running_loop().create_future()
        self.done = False  # the outcome is set (read at every line: a plain attribute)
        # Set when `acked` reaches `wake_at`, and when the stream ends: its runner's cue.
        self.wake = asyncio.Event()
        self.wake_at: int | None = None

    def peek(self) -> InFlight | None:
        """The next line to write, booked as it will be (its bytes, this stream, its file
        line number), or None when there is none.

        A line the board must never receive ends the stream as failed, unsent.
        """
        if self._next is None and not self.exhausted and not self.done:
            if not self._ahead and not self._read_ahead():
                self.exhausted = True
                return None
            entry = self._ahead.popleft()
            if isinstance(entry, tuple):
                number, invalid = entry
                self.finish(StreamEnd.FAILED, -32602, f"line {number}: {invalid.message}")
                return None
            self._next = entry
        return self._next

    def prefetch(self) -> None:
        """Read and encode up to LOOK_AHEAD lines ahead (the engine calls it after a write)."""
        while len(self._ahead) < LOOK_AHEAD and not self.done and self._read_ahead():
            pass

    def _read_ahead(self) -> bool:
        """One more line of the source onto the look-ahead; False once there is none."""
        if self._source_done:
            return False
        try:
            number, text = next(self._lines)
        except StopIteration:
            self._source_done = True
            return False
        try:
            encoded = self._encode(text, number if self.numbered else None)
        except InvalidCommand as exc:
            self._ahead.append((number, exc))  # refused when its turn comes: the lines before go
        else:
            self._ahead.append(InFlight(encoded, self, number))
        return True

    def take(self) -> None:
        """The peeked line was written."""
        entry = self._next
        assert entry is not None
        line = entry.line
        if (b"M" in line or b"m" in line) and _PROGRAM_PAUSE.search(line):
            self.program_pause_sent = True
        number = entry.file_line
        assert number is not None
        if number > self._sent_line:  # file lines only grow; a resume's preamble is line 0
            if self._first_line is None:
                self._first_line = number
            self._sent_line = number
        self._next = None
        self.sent += 1

    def acknowledged(self, file_line: int | None) -> None:
        self.acked += 1
        self.last_acked_line = file_line
        self._acked_lines.append(file_line)
        if self.wake_at is not None and self.acked >= self.wake_at:
            self.wake_at = None
            self.wake.set()

    def executing(self, file_line: int) -> None:
        """The board runs (or ran) this line. A number no line of this job carries is stale
        (a line before the job, or read ahead of what was sent) and is ignored."""
        first = self._first_line
        if first is None or not first <= file_line <= self._sent_line:
            return
        if file_line > (self.line_executed or 0):
            self.line_executed = file_line

    def acked_line(self, back: int) -> int | None:
        if back >= len(self._acked_lines):
            return None
        return self._acked_lines[-1 - back]

    def finish(self, end: StreamEnd, code: int | None = None, message: str | None = None) -> None:
        if not self.done:
            self.done = True
            self._next = None
            self._ahead.clear()
            self.result.set_result(StreamResult(end, code, message))
            self.wake.set()
