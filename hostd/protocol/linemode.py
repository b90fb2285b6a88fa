"""Line-mode flow control: at most `window` lines unanswered, each answer matched to its line.

Pure bookkeeping, no I/O: the engine asks `room`, records what it wrote
with `sent`, hands every `{r}` to `answered`, and calls `dropped` after `%`
or 0x04, when the board discards buffered lines without answering them.

Two budgets, one a kind of line. Data lines (G-code, `$`) wait in the
board's buffer for planner room: at most `window` of them are unanswered,
the line-mode window. Control lines (`{`) are read on every pass of the
board's main loop, ahead of waiting data (g2core.md section 7.1), so they
have a lane of their own, `control_window` deep: a flood of queries neither
takes the job's slots nor grows past what the board skips ahead of data
(at most 16 out-of-order lines). The daemon's own urgent lines (the status
probe, the handshake's settings) may go past the lane; they are few.

Matching answers to lines needs care, because the board does not answer in
the order it was written to. It runs a *control* line (one starting with
`{`) as soon as it has read it, ahead of *data* lines (G-code, `$`, `?`)
still waiting in its buffer for planner room (g2core.md section 7.1). Within
each kind the order holds. So there are two queues, and an answer belongs to
the only non-empty one; when both wait, the footer count decides (a data line
of L bytes is answered with L+1, a control line with L+2: its LF counts), and
if that is ambiguous, the body does (at jv 4 a data line's body holds nothing
but `n`).

A fence is a line written on the data port right behind a 0x04 (`fence`):
the board reads it only after that 0x04, which threw away every data line
written before it that was not read yet (docs/protocol.md, "A kill's
fence"). It is booked apart from both queues, outside their budgets: its
answer is known by its own count and body (`fence_answered`), and with it
the data lines booked before it that are still unanswered are known to be
discarded. Fences unanswered at once differ in their body (the caller asks
each for another key): a later 0x04 throws away an earlier fence still
unread, so an answer must say which fence it is.
"""

from __future__ import annotations

from collections import deque
from typing import Any

from hostd.protocol.messages import Response
from hostd.protocol.parser import plain_answer


class SenderError(Exception):
    """The sender's bookkeeping was asked to do something impossible: a daemon bug."""


class InFlight:
    """One line written and not yet answered."""

    __slots__ = ("control", "count", "file_line", "line", "own", "source")

    def __init__(
        self, line: bytes, source: Any = None, file_line: int | None = None, own: bool = False
    ) -> None:
        self.line = line  # as written, with its LF
        self.source = source  # whoever sent it: a job, a client request
        self.file_line = file_line  # for a job's line, its line number in the file
        self.own = own  # the daemon's own line (handshake, query, clear), not a client's or a job's
        # The board runs a control line out of order, as soon as it is read.
        self.control = line.startswith(b"{")
        # The footer count of its answer: its length without the LF, + 1 (+ 2 for a
        # control line, whose LF the board counts too).
        self.count = len(line) + 1 if self.control else len(line)

    def expected_count(self) -> int:
        return self.count

    def __repr__(self) -> str:
        return f"InFlight({self.line!r}, file_line={self.file_line}, own={self.own})"


class PlainLine(InFlight):
    """A job's data line that its dialect encoded in a block and found plain
    (`encode_job_block`): not a `{` line, not a `$` line, no program pause, nothing
    the dialect's flow control must look at. `Stream.take_run` takes it on its
    room alone."""

    __slots__ = ()
    file_line: int
    # The same for every one: read from the class, not stored a line (they shadow the slots).
    own = False
    control = False

    def __init__(self, line: bytes, source: Any, file_line: int) -> None:
        self.line = line
        self.source = source
        self.file_line = file_line
        self.count = len(line)


CONTROL_WINDOW = 4
# The plain answer to a job's line N<n> of `count` bytes at jv 4 (json_parser.cpp echoes
# the line number; docs/protocol.md): `pop_job_answers`' first test.
_JOB_ANSWER = b'{"r":{"n":%d},"f":[1,0,%d]}'


class LineModeSender:
    def __init__(self, window: int = 4, control_window: int = CONTROL_WINDOW) -> None:
        if window < 1 or control_window < 1:
            raise ValueError("window must be at least 1")
        self.window = window
        self.control_window = control_window
        self._data: deque[InFlight] = deque()
        self._control: deque[InFlight] = deque()
        # Each fence, the body keys its answer holds, and the data lines booked before it.
        self._fences: deque[tuple[InFlight, frozenset[str], tuple[InFlight, ...]]] = deque()

    def __len__(self) -> int:
        return len(self._data) + len(self._control) + len(self._fences)

    @property
    def has_room(self) -> bool:
        """Room for one more data line."""
        return len(self._data) < self.window

    @property
    def control_room(self) -> bool:
        """Room for one more control line in its lane."""
        return len(self._control) < self.control_window

    def room(self, line: bytes) -> bool:
        """Room for this line, by its kind."""
        return self.control_room if line.startswith(b"{") else self.has_room

    @property
    def data_in_flight(self) -> int:
        return len(self._data)

    def sent(self, entry: InFlight, *, urgent: bool = False) -> None:
        """Record a written line. An urgent one (the daemon's own) may go past its budget.

        The board still answers it with an `{r}`, so it still takes a slot;
        the count goes above the budget only until that answer arrives.
        """
        if urgent:
            (self._control if entry.control else self._data).append(entry)
        elif not self.book(entry):
            kind = "control lane" if entry.control else "window"
            budget = self.control_window if entry.control else self.window
            raise SenderError(f"{kind} of {budget} exceeded")

    def book(self, entry: InFlight) -> bool:
        """Record a written line if its kind has room; False, and nothing recorded, if not."""
        if entry.control:
            queue, budget = self._control, self.control_window
        else:
            queue, budget = self._data, self.window  # a job's line: every line of a job
        if len(queue) >= budget:
            return False
        queue.append(entry)
        return True

    def answered(self, response: Response) -> tuple[InFlight, list[InFlight]]:
        """The line this `{r}` answers, removed from the books, and the lines it skips.

        The board answered nothing for a skipped line (an answer too large for
        its buffer can vanish): when the count does not fit the oldest line
        waiting but fits a later one of the same kind exactly, the ones before
        it are given up, so no later answer is matched one line off. When it
        fits none, the oldest takes it, as the order says.
        """
        queue = self._queue_for(response)
        if not queue:
            raise SenderError(f"an answer with no line waiting: {response.raw!r}")
        skipped: list[InFlight] = []
        if queue[0].expected_count() != response.count:
            for index, entry in enumerate(queue):
                if entry.expected_count() == response.count:
                    skipped = [queue.popleft() for _ in range(index)]
                    break
        return queue.popleft(), skipped

    def pop_job_answer(self, count: int) -> InFlight | None:
        """`answered` in one look, for the common case: the oldest data line, taken off
        the books, if an answer of `count` can only be its answer (no control line
        waits, and the count fits the oldest) and it is a job's line (it has a file
        line); else None, nothing changed."""
        data = self._data
        if self._control or not data:
            return None
        entry = data[0]
        if entry.count != count or entry.file_line is None:
            return None
        data.popleft()
        return entry

    def book_run(self, entries: list[InFlight]) -> None:
        """Record job data lines written together; the caller took no more than `window`
        leaves room for (`Stream.take_run` with that room)."""
        data = self._data
        if len(data) + len(entries) > self.window:
            raise SenderError(f"window of {self.window} exceeded")
        data.extend(entries)

    def pop_job_answers(
        self, lines: list[bytes], start: int, job: object, *, whole: bool = False
    ) -> tuple[int, list[int]]:
        """`pop_job_answer` for each line from `start` on while each is the plain answer
        (`{"r":{"n":N},"f":[1,0,C]}`, status 0) of the oldest data line, a line of `job`:
        the index of the first line it did not take, and the file lines it answered.
        With `whole`, every line from `start` on or none (the express step).

        The steady state of a job, a read at a time: it stops, nothing changed for that
        line, at anything else (a report, an error, an answer with a control line
        waiting, a count that fits no line), which the caller reads in full.
        """
        if self._control:
            return start, []
        data = self._data
        answered: list[int] = []
        for line, entry in zip(lines[start:] if start else lines, data, strict=False):
            if entry.source is not job:
                break
            # What jv 4 answers a numbered line with, compared whole, at a third of the
            # cost of the match and its groups. Any other form (no `n` below jv 4, a
            # line of no N) is matched as before.
            if line != _JOB_ANSWER % (entry.file_line, entry.count):
                plain = plain_answer(line)
                if plain is None or plain[2] != b"0" or entry.count != int(plain[3]):
                    break
            answered.append(entry.file_line)  # type: ignore[arg-type]  # a job's line has one
        if whole and len(answered) != len(lines) - start:
            return start, []
        popleft = data.popleft
        for _ in answered:
            popleft()
        return start + len(answered), answered

    def fence(self, entry: InFlight, keys: frozenset[str]) -> None:
        """Book a fence written behind a 0x04 on the data port; its answer's body holds
        exactly `keys`, which no other fence unanswered holds. Outside both budgets:
        the daemon's own, one a kill."""
        self._fences.append((entry, keys, tuple(self._data)))

    @property
    def fences(self) -> int:
        """Fences written and not yet answered."""
        return len(self._fences)

    def fence_keys(self) -> set[frozenset[str]]:
        """The answer bodies' keys of the fences not yet answered."""
        return {keys for _, keys, _ in self._fences}

    def fence_answered(self, response: Response) -> tuple[InFlight, list[InFlight]] | None:
        """If this `{r}` answers a fence: that fence, and the data lines booked before it
        that are still unanswered (the 0x04 ahead of it discarded them), taken off the
        books with the fences before it. None, nothing changed, for any other answer.

        The answer is a fence's when its count and body keys are that fence's and it
        says OK; the caller picks fences no other line of its own or of a client's can
        be mistaken for (g2kills.py `_write_fence`).
        """
        if not self._fences or response.status:
            return None
        fences = self._fences
        found = next(
            (
                index
                for index, (entry, keys, _) in enumerate(fences)
                if response.count == entry.count and response.body.keys() == keys
            ),
            None,
        )
        if found is None:
            return None
        entry, _, before = fences[found]
        # The fences before it were thrown away unread by the 0x04 ahead of this one:
        # one read would have been answered first (a port's data lines keep order).
        for _ in range(found + 1):
            fences.popleft()
        data = self._data
        discarded: list[InFlight] = []
        # Booked before the fence, they are the oldest: answered ones are gone already.
        while data and any(line is data[0] for line in before):
            discarded.append(data.popleft())
        return entry, discarded

    def oldest_control(self) -> InFlight | None:
        """The control line the board is answering now, if any: the first unanswered one."""
        return self._control.popleft() if self._control else None

    def dropped(self) -> list[InFlight]:
        """After `%` or 0x04: the data lines the board discarded unanswered, oldest first.

        Control lines were run on arrival and are still answered.
        """
        lost = list(self._data)
        self._data.clear()
        return lost

    def pending(self) -> list[InFlight]:
        """Everything unanswered, for accounting when the link is lost."""
        return [*self._data, *self._control, *(fence for fence, _, _ in self._fences)]

    def clear(self) -> list[InFlight]:
        lost = self.pending()
        self._data.clear()
        self._control.clear()
        self._fences.clear()
        return lost

    def _queue_for(self, response: Response) -> deque[InFlight]:
        if not self._control:
            return self._data
        if not self._data:
            return self._control
        data_match = self._data[0].expected_count() == response.count
        control_match = self._control[0].expected_count() == response.count
        if data_match != control_match:
            return self._data if data_match else self._control
        return self._data if response.body.keys() <= {"n"} else self._control
