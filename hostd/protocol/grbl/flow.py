"""GrblSession's flow control: which line is written when (character counting).

A layer of `GrblSession` (session.py). A client's line is admitted when it
arrives (`send`) and again when it is written (`_pump`), against the state
and context of that moment. Lines go in order, a client's first, then the
job's, as long as the receive buffer has room for all the bytes unanswered
(`_room`; a ring of N bytes holds N - 1); none while a line writes EEPROM or
flash (send-response: bytes arriving meanwhile are lost), none while the
board holds or is locked out, none while a report is awaited. The answers
that free the buffer are read here when they are a job's plain `ok`s
(`_job_ok`, `_take_answers`): the per-line hot path.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from hostd.protocol.classes import CommandClass
from hostd.protocol.errors import Busy, Rejected
from hostd.protocol.grbl import codec
from hostd.protocol.grbl.books import _MAY_STORE, _REFUSED_BY_ALARM, GrblBooks
from hostd.protocol.linemode import InFlight
from hostd.protocol.program import MAX_LINE_NUMBER, NOT_PREFIXED, number_line, numbered_block
from hostd.protocol.states import LOCKOUTS, MachineState
from hostd.protocol.stream import Stream
from hostd.protocol.vocabulary import Context, Lane, Phase, Queued


class GrblFlow(GrblBooks):
    """Character-counted flow control: a client's lines and a job's (see `GrblSession`)."""

    def quiet(self) -> bool:
        """As every session's, but a query in flight (`$$`, `$#`, `$G`: views that move
        nothing) leaves the machine quiet: a resume's `job.start` reads the board first,
        and a status report read meanwhile must not make the machine busy, and the job
        refused, until the next report."""
        if self._inflight and not all(
            codec.classify(entry.line.decode("ascii", "replace")) is CommandClass.QUERY
            for entry in self._inflight
        ):
            return False
        return not self._outbox and not self._job_running() and not self.flushing()

    def numbers_lines(self) -> bool:
        """Unless `[OPT:]` said the build keeps no line number (classic grbl without
        USE_LINE_NUMBERS, its default): an N word then costs the receive buffer and the
        wire its bytes (a fifth of a short move's) and never comes back as `Ln:`."""
        return self.line_numbers is not False

    def encode_job_line(self, text: str, number: int | None = None) -> bytes:
        if number is not None and self.numbers_lines():
            if (
                text[:1] not in NOT_PREFIXED
                and 0 <= number <= MAX_LINE_NUMBER
                and text[-1:] != " "
                and "(" not in text
                and ";" not in text
            ):
                # `number_line`'s answer for almost every job line, and `codec.encode`'s
                # first branch on it: no comment to strip, no blank to strip at either end
                # (it starts with N; any other trailing blank fails the printable test).
                line = f"N{number} {text}"
                if len(line) < self.rx_size - 1 and codec.printable(line):
                    return (line + "\n").encode("ascii")
            text = number_line(text, number)
        return codec.encode(text, max_bytes=self.rx_size - 1)

    def encode_job_block(self, numbers: Sequence[int], texts: Sequence[str]) -> list[bytes] | None:
        """`encode_job_line` of each line, in one pass when every one takes its first
        branch above (or, unnumbered, is written as it is) and none may store
        (`_MAY_STORE`, which `_pump` must see); else None."""
        if self.numbers_lines():
            block = numbered_block(numbers, texts)
            plain = codec.plain_numbered_block
        else:  # the lines as they are
            block = "\n".join(texts) + "\n"
            plain = codec.plain_block
        if block is None or plain(block) is None:
            return None
        data = block.encode("ascii")
        if _MAY_STORE(data):  # found in the block if in any of its lines
            return None
        lines = data.splitlines(keepends=True)  # printable: no CR in any
        if len(lines) != len(texts) or max(map(len, lines)) > self.rx_size - 1:
            return None  # (a text of two lines, unnumbered, would pass the pattern)
        return lines

    def send(self, line: str, token: Any, *, operation: bool = False) -> None:
        self._require_ready()
        if self.halted:
            raise self._write_refused()
        text = line.strip()
        if text == "?":
            self._report_waiters.append(token)
            self._ask_report()
            return
        if self._held is not None:
            raise Busy(self._held)  # nothing is written until the operator resets
        cls = codec.classify(text)
        verdict = self._admit(cls, self.model.state)
        if verdict is not None:
            raise Rejected(verdict, self._locked_message())
        self._refuse_until_reset()
        encoded = codec.encode(text, max_bytes=self.rx_size - 1)
        if cls in (CommandClass.QUERY, CommandClass.CLEAR):
            self._outbox.append(Queued(encoded, cls, token, Context.ANY))
            return
        context = self._context()
        if operation and self._operation and context is Context.JOB:
            self._outbox.append(Queued(encoded, cls, token, Context.OPERATION))
        elif context is Context.JOB:
            raise Busy(f"{self.id} is running {'a job' if self._job_running() else 'an operation'}")
        elif context is Context.HOLD or self.model.state is MachineState.INTERLOCK:
            raise Busy(f"{self.id} is in a hold: grbl runs no line inside one; resume first")
        else:
            self._outbox.append(Queued(encoded, cls, token, context))

    def _refuse_until_reset(self) -> None:
        """After a critical alarm the board reads no line until it is reset (then `$X`)."""
        if self._needs_reset is not None:
            raise Rejected(
                _REFUSED_BY_ALARM,
                f"{self._locked_message()}: the controller reads nothing until a reset "
                "(machine.reset), then clear",
            )

    def _room(self, line: bytes) -> bool:
        return self._rx_used + len(line) <= self.rx_size - 1

    def _pump(self) -> None:
        if self.phase is not Phase.READY or self.halted or self.flushing():
            return
        if self._storing is not None:
            return  # bytes arriving while the board writes EEPROM are lost: wait for its answer
        state = self.model.state
        # Judged only when a client's line waits: most passes carry job lines alone.
        context = self._context() if self._outbox else Context.FREE
        while self._outbox:
            head = self._outbox[0]
            if not self._room(head.encoded):
                return  # in order: a client's lines never overtake each other
            if self._await_report and head.context is not Context.ANY:
                return
            if head.cls is CommandClass.CLEAR and self._inflight:
                return  # a stale line must not run after the unlock
            queued = self._outbox.popleft()
            if self._admissible(queued, state, context):
                self._book(queued.encoded, queued.token)
                if self._storing is not None:
                    return  # send-response: the next line waits for this one's answer
        stream = self.stream
        if stream is None or stream.done or self._job_lines_wait(stream, state):
            return
        # `_room` and `_special`'s first test written out: this loop runs for every job line.
        room = self.rx_size - 1
        inflight = self._inflight
        out = self._out
        data = Lane.DATA
        if self.fast_path:
            # The steady state: the plain lines ahead that the receive buffer has room
            # for, taken and booked together; the loop below goes on from the first line
            # it left (a `$` line, one that may store, one that does not fit).
            taken = self._take_run(stream)
            if taken:
                out.extend([(data, entry.line) for entry in taken])
        while True:
            entry = stream.peek()
            if entry is None:
                self._check_stream_complete()
                return
            line = entry.line
            if self._rx_used + len(line) > room:
                return
            stream.take()
            inflight.append(entry)
            self._rx_used += len(line)
            out.append((data, line))
            if (line[:1] == b"$" or _MAY_STORE(line)) and self._special(entry):
                return

    def _job_lines_wait(self, stream: Stream, state: MachineState | None) -> bool:
        """None of the job's lines may be written now (`_pump`'s and `express`'s)."""
        return stream.paused or self._await_report or state in _NO_JOB_LINES

    def _take_run(self, stream: Stream) -> list[InFlight]:
        """The plain lines ahead that the receive buffer has room for, taken and booked."""
        taken = stream.take_run(self.rx_size - 1 - self._rx_used, by_bytes=True, special=_MAY_STORE)
        if taken:
            self._inflight.extend(taken)
            self._rx_used += sum([len(entry.line) for entry in taken])
        return taken

    def _writes_wait(self) -> bool:
        """A stop or reset is under way, or a line writes EEPROM (send-response)."""
        return self.flushing() or self._storing is not None

    def _take_answers(
        self, lines: list[bytes], start: int, stream: Stream, *, whole: bool = False
    ) -> int:
        """`receive`'s `_job_ok` for a run of `ok`s, each the answer to the job's oldest
        line, booked together. Not while a line writes EEPROM or homes; a `$` line's
        `ok` is read in full."""
        if self._storing is not None or self._homing_lines:
            return start
        answered: list[int] = []
        freed = 0
        for line, entry in zip(lines[start:] if start else lines, self._inflight, strict=False):
            encoded = entry.line
            if line != b"ok" or entry.source is not stream or encoded[:1] == b"$":
                break
            freed += len(encoded)
            answered.append(entry.file_line)  # type: ignore[arg-type]  # a job's line has one
        if not answered or (whole and len(answered) != len(lines) - start):
            return start
        popleft = self._inflight.popleft
        for _ in answered:
            popleft()
        self._heard_at = self.clock()  # `receive`'s first steps, once for the run
        if self._silent_asks:
            self._silent_asks.clear()
        self._rx_used -= freed
        if self._said:
            self._said = []
        self._lines_in += len(answered)
        stream.acknowledged_run(answered)
        return start + len(answered)

    def _job_ok(self) -> bool:
        """An `ok` for the oldest line, a job's plain line: what `_answered` would do
        with it, without its message and its Response; False, and nothing done, for
        any other line (no line waiting, a `$` line, one that homes or stores)."""
        inflight = self._inflight
        if not inflight:
            return False
        entry = inflight[0]
        line = entry.line
        if (
            entry.file_line is None
            or line[:1] == b"$"
            or entry is self._storing
            or (self._homing_lines and codec.homes(line))
        ):
            return False
        inflight.popleft()
        self._rx_used -= len(line)
        if self._said:
            self._said = []  # what the board printed before it: a job line's ok carries none
        self._lines_in += 1
        if entry.source.acknowledged(entry.file_line):
            self._check_stream_complete()
        return True


# The states in which none of a job's lines is written: a lockout, a hold, a door open.
_NO_JOB_LINES = LOCKOUTS | {MachineState.HOLD, MachineState.INTERLOCK}
