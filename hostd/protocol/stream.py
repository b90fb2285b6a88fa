"""A job's read position, as its session holds it: plain data, no file, no future.

The session owns what it decides about a job: which line goes next, how
many are sent, answered, refused, discarded, which one the board runs, and
how the job ended. The caller (the machine layer) owns the file: it feeds
lines in with `feed` while `wanted()` says there is room ahead, says
`end_of_input()` when the file has no more, and reads the counts back. The
session tells the job's end as an event (`StreamEnded`), never by
resolving anything of its caller's.

Lines are encoded when fed, so that the path from an answer to the next line
written carries no encoding: the caller keeps up to `look_ahead` lines ahead
of what the flow control has taken, fed in blocks (once no more than a
quarter of them are left), which the dialect encodes in one pass when every
line of the block is plain (`encode_block`). When the flow control has room
and nothing ahead (`starved`), the caller feeds more and the session is
pumped again in the same step. A line that may not be sent is refused when
its turn comes, not when it is fed: the lines before it still go.

Counts only move forward: `sent` when a line is written, `acked` when the
board answers it with status 0. Every sent line ends in exactly one of
`acked`, `rejected`, `discarded`, or is still unanswered when the link is
lost. The outcome is set once.

A line fed with `hold` is a hold point (a tool change, hostd/machine/toolchange.py):
when its turn comes `peek` hands out nothing and `held` names it, until the
caller has the session `release` it. It is not the job's pause (`paused`, the
user's `!` to `~`): neither clears the other, so a resume never carries a job
past a hold. Held lines are no underflow (`lines_on_host` is False): the host
keeps them back on purpose.

`line_executed` is the file line the board said it was executing (its N word in
a status report; the session decides which reports say so, per dialect). It
only moves forward and never past the last line sent: every value it takes is
a lower bound of the truth, so it never claims more than the board ran.
"""

from __future__ import annotations

import re
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from itertools import repeat

from hostd.protocol.commands import InvalidCommand, encode_line
from hostd.protocol.linemode import InFlight, PlainLine
from hostd.protocol.vocabulary import StreamEnd, StreamResult

_ACKED_KEPT = 512  # answered lines remembered: more than any planner holds blocks
# Lines fed and encoded ahead of the flow control's room, at most: a job's are fed in
# blocks of about this many, not a line a read.
LOOK_AHEAD = 64
# M0, M1 or M60, not inside a number. The M first, then what comes before it: a pattern that
# starts with a look-behind is tried at every byte (twice the time on a job's block).
_PROGRAM_PAUSE = re.compile(rb"[mM](?<![0-9.][mM])0*(?:0|1|60)(?![0-9.])")
_DOLLAR = ord("$")
# Bytes looked for as their values: `77 in line` is a byte search, where `b"M" in line`
# first tries the bytes as an integer, and raises and clears a TypeError, each time
# (CPython 3.11 `_Py_bytes_contains`): 20 ns against 230 ns, at every job line.
_M, _m = ord("M"), ord("m")


class Stream:
    """One job's lines ahead and its counts; the session moves it, the caller feeds it."""

    def __init__(
        self,
        job_id: int | None = None,
        encode: Callable[[str, int | None], bytes] | None = None,
        *,
        numbered: bool = False,
        encode_block: Callable[[Sequence[int], Sequence[str]], list[bytes] | None] | None = None,
        look_ahead: int = LOOK_AHEAD,
    ) -> None:
        # The dialect's: what a job line becomes on the wire; `numbered` gives each line its
        # file line number as an N word, so that status reports say which line runs.
        self._encode = encode or (lambda text, _number: encode_line(text))
        self.numbered = numbered
        # The dialect's for a block of numbered lines that are all plain: each encoded as
        # `encode` would, or None (then each line goes through `encode`).
        self._encode_block = encode_block if numbered else None
        self.look_ahead = look_ahead
        self._refill_at = look_ahead // 4  # fed again once no more are ahead
        self.job_id = job_id  # the job row it belongs to, for the logs
        self._next: InFlight | None = None
        # Fed ahead: a line as the flow control books it, or why it may not be sent, or
        # (file line, None): a hold point before that line.
        self._ahead: deque[InFlight | tuple[int, InvalidCommand | None]] = deque()
        # The caller has no more lines (read at every read of a job: a plain attribute).
        self.input_ended = False
        self.starved = False  # the flow control asked for a line and none was ahead
        self.refused: tuple[int, str] | None = None  # the file line whose turn came, unsendable
        self.sent = 0
        self.acked = 0  # answered with status 0
        self.rejected = 0  # answered with a non-zero status
        self.discarded = 0  # dropped unanswered by the board's flush or kill
        self.last_acked_line: int | None = None
        self.line_executed: int | None = None
        self._sent_line = 0  # the highest file line number written
        self._first_line: int | None = None  # the first one (a resume's preamble is line 0)
        self._acked_lines: deque[int | None] = deque(maxlen=_ACKED_KEPT)
        # M0/M1/M60s written that the board has not yet stopped at: its next stop is the
        # program's pause, not an underflow (g2status.py `_on_state`); and whether it
        # stands at one now, until a report says it runs again.
        self.program_pauses = 0
        self.at_program_pause = False
        self.paused = False  # from the job's `!` to its `~`: none of its lines is written
        self.held: int | None = None  # the file line a hold point keeps back, its turn come
        self.result: StreamResult | None = None
        self.done = False  # the outcome is set (read at every line: a plain attribute)
        self.full = False  # the last `take_run` stopped at the room alone

    # -- the caller's side ---------------------------------------------------------

    def wanted(self) -> int:
        """How many more lines to feed now: up to `look_ahead` ahead once no more than a
        quarter of them are left, none once the input ended."""
        if self.done or self.input_ended:
            return 0
        ahead = len(self._ahead) + (self._next is not None)  # a line peeked is still ahead
        return self.look_ahead - ahead if ahead <= self._refill_at else 0

    def feed(self, number: int, text: str, *, hold: bool = False) -> None:
        """One more line of the job: its file line number and its text. `hold`: the job
        holds before it until `release` (a tool change)."""
        self.starved = False
        if hold:
            self._ahead.append((number, None))
        try:
            encoded = self._encode(text, number if self.numbered else None)
        except InvalidCommand as exc:
            self._ahead.append((number, exc))  # refused when its turn comes: the lines before go
        else:
            self._ahead.append(InFlight(encoded, self, number))

    def feed_many(self, lines: list[tuple[int, str]]) -> None:
        """`feed` for each (file line number, text), none of them a hold point: a job's
        file, a look-ahead's worth at a time, without a call a line."""
        block = self._encode_block
        if block is not None and lines:
            numbers = [number for number, _ in lines]
            written = block(numbers, [text for _, text in lines])
            if written is not None:
                self.starved = False
                # No program pause among them: each is a plain line, taken on its room alone.
                data = b"".join(written)
                pause = (_M in data or _m in data) and _PROGRAM_PAUSE.search(data)
                kind = InFlight if pause else PlainLine
                self._ahead.extend(map(kind, written, repeat(self), numbers))
                return
        encode = self._encode
        numbered = self.numbered
        append = self._ahead.append
        for number, text in lines:
            self.starved = False
            try:
                encoded = encode(text, number if numbered else None)
            except InvalidCommand as exc:
                append((number, exc))  # refused when its turn comes: the lines before go
            else:
                append(InFlight(encoded, self, number))

    def feed_all(self, lines: Iterable[tuple[int, str]]) -> Stream:
        """Every line at once, and the end of input (a short job, or a test)."""
        for number, text in lines:
            self.feed(number, text)
        self.end_of_input()
        return self

    def end_of_input(self) -> None:
        """The caller has no more lines: once those fed are written, the job is all sent."""
        self.input_ended = True
        self.starved = False

    @property
    def exhausted(self) -> bool:
        """Every line was handed out, and no more will be fed."""
        return self.input_ended and self._next is None and not self._ahead

    # -- the session's side --------------------------------------------------------

    def peek(self) -> InFlight | None:
        """The next line to write, booked as it will be (its bytes, this stream, its file
        line number), or None when there is none now.

        None with `refused` set: the next line must never reach the board; the
        session ends the stream failed. None with `starved`: the caller has more.
        """
        entry = self._next
        if entry is None and not self.done:
            ahead = self._ahead
            if not ahead:
                self.starved = not self.input_ended
                return None
            first = ahead[0]
            if isinstance(first, tuple):
                number, invalid = first
                if invalid is None:  # a hold point: nothing goes until it is released
                    self.held = number
                else:
                    self.refused = (number, invalid.message)
                return None
            entry = self._next = ahead.popleft()  # type: ignore[assignment]
        return entry

    def lines_on_host(self) -> bool:
        """Lines of the job wait on the host that the board could run now (not a `{`-line,
        which waits for the lines before it on purpose)."""
        entry = self.peek()
        if entry is not None:
            return not entry.control
        return self.refused is None and self.held is None and not self.input_ended

    def release(self) -> None:
        """The hold point whose turn came is passed: the line after it goes next."""
        if self.held is None:
            return
        first = self._ahead[0]
        assert isinstance(first, tuple) and first[1] is None
        self._ahead.popleft()
        self.held = None

    def take(self) -> None:
        """The peeked line was written."""
        entry = self._next
        assert entry is not None
        line = entry.line
        if (_M in line or _m in line) and _PROGRAM_PAUSE.search(line):
            self.program_pauses += 1
        number = entry.file_line
        assert number is not None
        if number > self._sent_line:  # file lines only grow; a resume's preamble is line 0
            if self._first_line is None:
                self._first_line = number
            self._sent_line = number
        self._next = None
        self.sent += 1

    def take_run(
        self, room: int, *, by_bytes: bool = False, special: Callable[[bytes], object] | None = None
    ) -> list[InFlight]:
        """The steady state's `peek` and `take`, for as many of the next lines as `room`
        holds (lines, or with `by_bytes` their bytes): each taken as `take` takes it.

        Stops, taking nothing more, before whatever the session must look at itself:
        a hold point or a refused line, a control (`{`) line, a `$` line, a line
        `special` matches (the dialect's own: grbl's storing lines), the room used up, the
        look-ahead empty (`starved` is then the next `peek`'s to say). What it leaves
        is exactly what `peek` and `take`, line by line, would leave there.

        `full` says afterwards whether it stopped at the room alone, before a line that
        `peek` would hand out as it is: the writer's loop would write nothing more and
        `peek` change nothing, so the step may end here (the engine's express step).
        """
        self.full = False
        if self.done:
            return []
        ahead = self._ahead
        if self._next is not None:  # peeked, not taken (the room was used up): first again
            ahead.appendleft(self._next)
            self._next = None
        taken: list[InFlight] = []
        append = taken.append
        popleft = ahead.popleft
        pause = _PROGRAM_PAUSE.search
        sent_line = self._sent_line
        first_line = self._first_line
        while ahead and room > 0:
            entry = ahead[0]
            if plain := type(entry) is PlainLine:
                pass  # nothing to look at but its room (`encode_block`)
            elif isinstance(entry, tuple) or entry.control:  # a hold point, a refused line
                break
            else:
                line = entry.line
                if line[0] == _DOLLAR or (special is not None and special(line)):
                    break
            if by_bytes:
                room -= entry.count  # a data line's bytes
                if room < 0:
                    self.full = True  # this line does not fit
                    break
            else:
                room -= 1
            popleft()
            append(entry)
            if not plain and (_M in line or _m in line) and pause(line):
                self.program_pauses += 1
            number: int = entry.file_line  # type: ignore[assignment]  # a job's line has one
            if number > sent_line:  # file lines only grow; a resume's preamble is line 0
                if first_line is None:
                    first_line = number
                sent_line = number
        if room == 0 and ahead and not isinstance(ahead[0], tuple):
            self.full = True
        self._sent_line = sent_line
        self._first_line = first_line
        self.sent += len(taken)
        return taken

    def acknowledged_run(self, file_lines: list[int]) -> None:
        """`acknowledged` for each of these lines, answered in this order, while the
        job's input has not ended and no refused line's turn has come (the session
        checks: nothing is to be checked for the job's end then)."""
        self.acked += len(file_lines)
        self.last_acked_line = file_lines[-1]
        self._acked_lines.extend(file_lines)

    def acknowledged(self, file_line: int | None) -> bool:
        """A sent line was answered with status 0. True if the job may be complete now
        (its input ended, or a refused line's turn came): the session checks then."""
        self.acked += 1
        self.last_acked_line = file_line
        self._acked_lines.append(file_line)
        return self.input_ended or self.refused is not None

    def executing(self, file_line: int) -> None:
        """The board runs (or ran) this line. A number no line of this job carries is stale
        (a line before the job, or fed ahead of what was sent) and is ignored."""
        first = self._first_line
        if first is None or not first <= file_line <= self._sent_line:
            return
        if file_line > (self.line_executed or 0):
            self.line_executed = file_line

    def acked_line(self, back: int) -> int | None:
        """The file line of the answered line `back` answers before the last (0: the last)."""
        if back >= len(self._acked_lines):
            return None
        return self._acked_lines[-1 - back]

    def finish(self, end: StreamEnd, code: int | None = None, message: str | None = None) -> bool:
        """Set the outcome once; False, and nothing changed, if it was set already.

        Only the session calls it, and it tells the end as a `StreamEnded` event.
        """
        if self.done:
            return False
        self.done = True
        self._next = None
        self._ahead.clear()
        self.held = None
        self.result = StreamResult(end, code, message)
        return True
