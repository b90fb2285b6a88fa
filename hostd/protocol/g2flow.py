"""G2Session's flow control: which line is written when, on which lane.

A layer of `G2Session` (g2core.py). A client's line is admitted twice: when it
arrives (`send`) and again when it is written (`_pump`), against the state and
context of that moment. Queries go as strict JSON GETs, which the board runs
at once; in-hold lines go through the bounded control lane, past the window;
action lines wait in the outbox, in order, for room in the line-mode window
(`LineModeSender`, linemode.py); then the job's lines, as many as the window
has room for, none while a flush awaits its proof, an exception report
awaits a status report, or the board holds or is locked out.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from hostd.protocol.classes import CommandClass, admit, classify
from hostd.protocol.commands import MAX_LINE_BYTES, encode_get, encode_line, validate_line
from hostd.protocol.errors import Rejected
from hostd.protocol.g2holds import G2Holds
from hostd.protocol.gcode import plain_match, plain_numbered_block
from hostd.protocol.linemode import InFlight
from hostd.protocol.program import MAX_LINE_NUMBER, NOT_PREFIXED, number_line, numbered_block
from hostd.protocol.relaxed import parse_relaxed
from hostd.protocol.states import LOCKOUTS, MachineState
from hostd.protocol.stream import Stream
from hostd.protocol.vocabulary import Context, Lane, Phase, Queued

# The states in which none of a job's lines is written: a lockout (the board drains and
# rejects them) and a hold. One set, asked once a read (`_job_lines_wait`).
_NO_JOB_LINES = LOCKOUTS | {MachineState.HOLD}


class G2Flow(G2Holds):
    """Line-mode flow control: a client's lines and a job's (see `G2Session`)."""

    # -- requests --------------------------------------------------------------

    def send(self, line: str, token: Any, *, operation: bool = False) -> None:
        """One line from a client; its answer or error comes back as `Settled(token, ...)`.

        Refused at once (raises) if it may not be written in this state.
        `operation`: the line is the running operation's own (a settings
        batch, a jog's G90), not a client's; it fits while that operation runs.
        """
        self._require_ready()
        if self.halted:
            raise self._write_refused()
        validate_line(line)
        cls = classify(line)
        text = line.strip()
        verdict = admit(cls, self.model.state)
        if verdict is not None:
            raise Rejected(verdict, self._locked_message())
        if cls is CommandClass.QUERY:
            # As a JSON GET it is run on arrival: it never waits behind queued G-code.
            self._lane.append(Queued(_as_json_query(text), cls, token, Context.ANY))
        elif cls is CommandClass.CLEAR:
            self._outbox.append(Queued(encode_line(text), cls, token, Context.ANY))
        elif operation and self._operation and self._context() is Context.JOB:
            self._outbox.append(Queued(encode_line(text), cls, token, Context.OPERATION))
        else:
            self._admit_action(text, cls, token)

    def _admit(self, cls: CommandClass, state: MachineState | None) -> int | None:
        return admit(cls, state)

    def encode_job_line(self, text: str, number: int | None = None) -> bytes:
        if number is not None:
            if text[:1] not in NOT_PREFIXED and 0 <= number <= MAX_LINE_NUMBER:
                # `number_line`'s answer for almost every job line, and `encode_line`'s
                # first branch on it (a numbered line never starts with one of _TEXT_LEADS).
                line = f"N{number} {text}"
                if len(line) <= MAX_LINE_BYTES and plain_match(line) is not None:
                    return (line + "\n").encode("ascii")
            text = number_line(text, number)
        return encode_line(text)

    def encode_job_block(self, numbers: Sequence[int], texts: Sequence[str]) -> list[bytes] | None:
        """`encode_job_line` of each numbered line, in one pass when all are plain (the
        first branch above for every one of them); else None."""
        block = numbered_block(numbers, texts)
        if block is None or plain_numbered_block(block) is None:
            return None
        lines = block.encode("ascii").splitlines(keepends=True)  # plain: no CR in any
        if max(map(len, lines)) > MAX_LINE_BYTES + 1:
            return None
        return lines

    def _job_lines_wait(self, stream: Stream, state: MachineState | None) -> bool:
        """None of the job's lines may be written now (`_pump`'s and `express`'s)."""
        return (
            stream.paused
            or self._await_report
            or state in _NO_JOB_LINES
            or bool(self.model.hold)  # a hold at rest (101.05+) shows in `hold` alone
        )

    def _take_run(self, stream: Stream) -> list[InFlight]:
        """The plain lines ahead that the window has room for, taken and booked."""
        sender = self.sender
        taken = stream.take_run(sender.window - sender.data_in_flight)
        if taken:
            sender.book_run(taken)
        return taken

    def _writes_wait(self) -> bool:
        """A flush awaits its proof, or a client's line waits for the control lane."""
        return self._flush is not None or bool(self._lane)

    def data_to_send(self) -> list[tuple[Lane, bytes]]:
        out = super().data_to_send()
        if self._flush is not None:
            self._flush_out = True  # from now on a report may be the flush's proof
        return out

    # -- writing ---------------------------------------------------------------

    def _pump(self) -> None:
        """Fill the lane and the window: client lines first, then the job's lines.

        Every waiting line is admitted again here, against the state and
        context of this moment.
        """
        if self.phase is not Phase.READY or self.halted:
            return
        state = self.model.state
        # Judged only when a client's line waits: most passes carry job lines alone.
        context = self._context() if self._lane or self._outbox else Context.FREE
        flushing = self._flush is not None
        unsure = flushing or self._await_report  # the board may be anywhere now
        lane = self._lane
        sender = self.sender
        while lane and sender.control_room:
            if unsure and lane[0].context is not Context.ANY:
                break  # queries run now; an in-hold line waits to see where the board is
            queued = lane.popleft()
            if self._admissible(queued, state, context):
                self._book(queued.encoded, queued.token, Lane.CONTROL)
        if flushing:
            return  # no data line until the board shows what it discarded
        while self._outbox:
            head = self._outbox[0]
            if not sender.room(head.encoded):
                return  # in order: a client's lines never overtake each other
            waits = (Context.FREE, Context.HOLD, Context.OPERATION)
            if self._await_report and head.context in waits:
                return  # an exception report: actions wait for the next status report
            if head.cls is CommandClass.CLEAR and not self.no_data_in_flight():
                return  # a stale line must not run after the clear
            if head.cls is CommandClass.CLEAR and self._alarm_kill_due:
                # A 101.05+ alarm's hold still runs: the board is in ALARM only once it
                # holds and has killed the job (cycle_feedhold.cpp:353-361, `_run_alarm`),
                # and `cm_clear` does nothing before (alarm.cpp:83-95). Written now, the
                # clear would be answered OK and lost; it goes after the board's 207.
                return
            queued = self._outbox.popleft()
            if self._admissible(queued, state, context):
                # A clear goes on the data port, behind the lines it ends (g2core.md 9).
                where = Lane.DATA if queued.cls is CommandClass.CLEAR else _lane_of(queued.encoded)
                self._book(queued.encoded, queued.token, where, own=queued.own)
        stream = self.stream
        if stream is None or stream.done or self._job_lines_wait(stream, state):
            return
        out = self._out
        data = Lane.DATA
        if self.fast_path:
            # The steady state: the plain lines ahead that the window has room for, taken
            # and booked together; the loop below goes on from the first line it left.
            taken = self._take_run(stream)
            if taken:
                out.extend([(data, entry.line) for entry in taken])
        book = sender.book
        while True:
            entry = stream.peek()
            if entry is None:
                self._check_stream_complete()
                return
            if entry.control and (sender.data_in_flight or sender.fences):
                # The board reads a `{`-line ahead of data lines still waiting: a job's
                # JSON line would run before the moves written before it (xio.cpp:789).
                # A kill's fence is a data line still waiting.
                return
            if not book(entry):  # a job may hold `{`-lines: they take the control lane
                return
            stream.take()
            out.append((data, entry.line))


def _lane_of(encoded: bytes) -> Lane:
    return Lane.CONTROL if encoded.startswith(b"{") else Lane.DATA


def _as_json_query(text: str) -> bytes:
    """Every query as a strict JSON GET, which the board runs at once on any port."""
    if text == "?":
        return encode_get("sr")
    if text.startswith("$"):
        return encode_get(text[1:].strip().lower())
    obj = parse_relaxed(text)
    return encode_get(*obj) if obj else encode_line(text)
