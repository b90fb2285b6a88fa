"""The toy's session: a send-response line protocol on `SessionBase`, in ~200 lines.

One line unanswered at a time (`ok` or `err N` answers it); a status report
`<STATE x y z n>` answers a realtime `?`, asked every `status_interval`; an
`alarm N` line puts the board in ALARM, left by `UNLOCK`; 0x18 resets it and
it greets with `hello toy` again. Everything hostd needs of a dialect's
session, and nothing of g2core's or grbl's.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import Any

from hostd.protocol.classes import CommandClass, admit
from hostd.protocol.commands import InvalidCommand, Realtime, Refusal
from hostd.protocol.errors import Busy, ControllerError, MachineError, NotConnected, Rejected
from hostd.protocol.gcodestate.resume import Board
from hostd.protocol.limits import MachineLimits
from hostd.protocol.linemode import InFlight
from hostd.protocol.messages import JsonObject, Response
from hostd.protocol.program import number_line
from hostd.protocol.session import SessionBase
from hostd.protocol.states import MachineState
from hostd.protocol.stream import Stream
from hostd.protocol.vocabulary import (
    Context,
    Excepted,
    Lane,
    Phase,
    Queued,
    Ready,
    Reported,
    StreamEnd,
)
from tests.toydialect.words import MAX_LINE, STATES, alarm_text, error_text


def encode(text: str, max_bytes: int = MAX_LINE) -> bytes:
    """A line as the toy takes it: printable ASCII, within `max_bytes` with its LF."""
    if not text.isascii() or not text.isprintable() or any(c in text for c in "?!~"):
        raise InvalidCommand(Refusal.UNREADABLE, "the toy reads printable ASCII, no ? ! ~")
    encoded = text.encode() + b"\n"
    if len(encoded) > max_bytes:
        raise InvalidCommand(Refusal.TOO_LONG, f"longer than the toy takes ({max_bytes} bytes)")
    return encoded


def classify(text: str) -> CommandClass:
    return CommandClass.CLEAR if text.upper() == "UNLOCK" else CommandClass.ACTION


class ToySession(SessionBase):
    def __init__(
        self,
        machine_id: str,
        *,
        status_interval: float = 0.25,
        handshake_timeout: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(machine_id, clock)
        self.status_interval = status_interval
        self.handshake_timeout = handshake_timeout
        self._inflight: InFlight | None = None
        self._handshake_deadline: float | None = None
        self._next_poll = 0.0
        self._resetting = False
        self._report_waiters: list[Any] = []

    # -- the dialect's parts ---------------------------------------------------

    def _admit(self, cls: CommandClass, state: MachineState | None) -> int | None:
        return admit(cls, state)

    def flushing(self) -> bool:
        return self._resetting

    def no_data_in_flight(self) -> bool:
        return self._inflight is None

    def unanswered(self) -> int:
        return 0 if self._inflight is None else 1

    def encode_job_line(self, text: str, number: int | None = None) -> bytes:
        return encode(text if number is None else number_line(text, number))

    def jog_lines(self, axes: Mapping[str, float], feed: float) -> list[str]:
        raise InvalidCommand(Refusal.UNREADABLE, "the toy does not jog")

    def line_limit(self) -> int:
        return MAX_LINE

    def status_text(self, code: int) -> str:
        return error_text(code)

    def alarm_line(self) -> str:
        return "ALARM"

    def settings_read(self, keys: list[str]) -> list[str]:
        if keys:
            raise InvalidCommand(Refusal.UNREADABLE, "the toy has no settings")
        return []  # its limits: none to read

    def settings_write(self, values: Mapping[str, bool | int | float | str]) -> list[str]:
        raise InvalidCommand(Refusal.UNREADABLE, "the toy has no settings")

    def settings_found(self, keys: list[str], bodies: list[JsonObject]) -> dict[str, Any]:
        return {}

    def limit_settings(self) -> list[str]:
        return []

    def machine_limits(self, found: Mapping[str, Any]) -> MachineLimits:
        return MachineLimits()

    def offset_reads(self) -> list[str]:
        return []

    def board_offsets(self, bodies: list[JsonObject]) -> Board:
        return Board({}, {}, None)

    # -- the connection ----------------------------------------------------------

    def open(self, *, rebooting: bool = False) -> None:
        self.phase = Phase.HANDSHAKE
        self._closing_reason = None
        self._handshake_deadline = self.clock() + self.handshake_timeout
        self._ask_report()  # the first report ends the handshake

    def close(self, reason: str, *, restarted: bool = False) -> None:
        self.phase = Phase.CLOSED
        self._handshake_deadline = None
        self._resetting = False
        self._forget(NotConnected(f"link lost: {reason}"))
        self._end_stream_on_close(reason, restarted)
        self._out.clear()
        self.model.reset()

    def _forget(self, error: MachineError) -> None:
        entry, self._inflight = self._inflight, None
        if entry is not None:
            if entry.file_line is not None:
                entry.source.discarded += 1
            else:
                self._settle(entry.source, error)
        while self._outbox:
            self._settle(self._outbox.popleft().token, error)
        for token in self._report_waiters:
            self._settle(token, error)
        self._report_waiters.clear()
        self._await_report = self._awaiting_rest = False

    def next_deadline(self) -> float | None:
        if self._closing_reason is not None:
            return None
        return min(d for d in (self._handshake_deadline, self._next_poll) if d is not None)

    def tick(self) -> None:
        now = self.clock()
        if self._closing_reason is not None:
            return
        if self._handshake_deadline is not None and now >= self._handshake_deadline:
            self._closing(f"no toy report within {self.handshake_timeout:g} s")
            return
        if now >= self._next_poll:
            self._ask_report()

    # -- reading -----------------------------------------------------------------

    def receive(self, line: bytes) -> None:
        text = line.decode("ascii", "replace").strip()
        if text == "ok" or text.startswith("err "):
            self._answered(0 if text == "ok" else int(text[4:]), line)
        elif text.startswith("<") and text.endswith(">"):
            self._on_report(text[1:-1].split())
        elif text.startswith("alarm "):
            self._on_alarm(int(text[6:]))
        elif text.startswith("hello toy"):
            self._on_banner()

    def _answered(self, status: int, raw: bytes) -> None:
        entry, self._inflight = self._inflight, None
        if entry is None:
            self._detected("lexical", None, f"an answer with no line waiting: {raw!r}")
            return
        response = Response({}, status, 0, raw)
        if entry.file_line is None:
            self._settle(entry.source, response)
            return
        stream: Stream = entry.source
        if response.ok:
            stream.acknowledged(entry.file_line)
            self._check_stream_complete()
            return
        stream.rejected += 1
        self._end_stream(
            stream,
            StreamEnd.FAILED,
            ControllerError.code,
            f"line {entry.file_line}: controller answered err {status}: {error_text(status)}",
        )

    def _on_report(self, parts: list[str]) -> None:
        if len(parts) != 5 or parts[0] not in STATES:
            self._detected("lexical", None, f"a report the toy never prints: {parts!r}")
            return
        fields: dict[str, Any] = {"stat": int(STATES[parts[0]])}
        fields |= {f"pos{a}": float(v) for a, v in zip("xyz", parts[1:4], strict=True)}
        fields["line"] = int(parts[4])
        before = self.model.state
        changed = self.model.apply_status(fields)
        self._await_report = False
        if changed is not None:
            self._on_state(changed, before)
        if self.stream is not None and not self.stream.done and fields["line"] > 0:
            self.stream.executing(fields["line"])
        self._events.append(Reported(fields, self.model.snapshot()))
        waiters, self._report_waiters = self._report_waiters, []
        for token in waiters:
            self._settle(token, Response({"report": parts}, 0, 0, b"?"))
        if self._awaiting_rest:
            self._check_stream_complete(reported=True)
        if self.phase is Phase.HANDSHAKE and not self._resetting:
            self.phase = Phase.READY
            self._handshake_deadline = None
            self._events.append(Ready())

    def _on_state(self, state: MachineState, before: MachineState | None) -> None:
        if state.is_lockout:
            self._drain_for_lockout(state, error_text)
        self._recheck_waiting()

    def _on_alarm(self, code: int) -> None:
        report = {"alarm": code, "msg": alarm_text(code)}
        self.model.last_exception = report
        self._events.append(Excepted(report))
        before, self.model.state = self.model.state, MachineState.ALARM
        self._on_state(MachineState.ALARM, before)
        self._await_report = True
        self._ask_report()

    def _on_banner(self) -> None:
        """A reset (ours, or the board's): it forgot every line; a report makes it ready."""
        self._resetting = False
        if self.stream is not None and not self.stream.done:
            self._end_stream(self.stream, StreamEnd.FAILED, 1005, "the controller was reset")
        self._forget(ControllerError(0, "discarded by the controller's reset"))
        self.model.state = None
        self.phase = Phase.HANDSHAKE
        self._handshake_deadline = self.clock() + self.handshake_timeout
        self._ask_report()

    # -- writing -------------------------------------------------------------------

    def _pump(self) -> None:
        if self.phase is not Phase.READY or self.halted or self._inflight is not None:
            return
        if self._resetting:
            return
        state, context = self.model.state, self._context()
        while self._outbox and self._inflight is None:
            queued = self._outbox.popleft()
            if self._admissible(queued, state, context):
                self._write(InFlight(queued.encoded, queued.token))
        stream = self.stream
        if (
            self._inflight is not None
            or stream is None
            or stream.done
            or stream.paused
            or self._await_report
            or (state is not None and (state.is_lockout or state is MachineState.HOLD))
        ):
            return
        entry = stream.peek()
        if entry is None:
            self._check_stream_complete()
            return
        stream.take()
        self._write(entry)

    def _write(self, entry: InFlight) -> None:
        self._inflight = entry
        self._out.append((Lane.DATA, entry.line))

    def _ask_report(self) -> None:
        self._next_poll = self.clock() + self.status_interval
        self._out.append((Lane.REALTIME, b"?"))

    def _query_status(self) -> None:
        if self.phase is not Phase.CLOSED:
            self._ask_report()

    def _stop_board(self) -> None:
        self.reset()  # the toy empties itself only by a reset

    # -- requests --------------------------------------------------------------------

    def send(self, line: str, token: Any, *, operation: bool = False) -> None:
        self._require_ready()
        if self.halted:
            raise self._write_refused()
        text = line.strip()
        if text == "?":
            self._report_waiters.append(token)
            self._ask_report()
            return
        cls = classify(text)
        verdict = self._admit(cls, self.model.state)
        if verdict is not None:
            raise Rejected(verdict, self._locked_message())
        encoded = encode(text)
        context = self._context()
        if cls is CommandClass.CLEAR:
            self._outbox.append(Queued(encoded, cls, token, Context.ANY))
        elif operation and self._operation and context is Context.JOB:
            self._outbox.append(Queued(encoded, cls, token, Context.OPERATION))
        elif context is Context.JOB:
            raise Busy(f"{self.id} is running a job")
        elif context is Context.HOLD:
            raise Busy(f"{self.id} is in a hold: the toy runs no line inside one")
        else:
            self._outbox.append(Queued(encoded, cls, token, context))

    def _realtime(self, command: Realtime) -> None:
        if command is Realtime.FEEDHOLD:
            self._out.append((Lane.REALTIME, b"!"))
        elif command is Realtime.CYCLE_START:
            self._out.append((Lane.REALTIME, b"~"))
        elif command is Realtime.ENQUIRY:
            self._ask_report()
        elif command is Realtime.RESET:
            self.reset()
        else:  # no flush, no kill: the toy empties itself by a reset
            if self.stream is not None and not self.stream.done:
                self._end_stream(self.stream, StreamEnd.CANCELLED, None, "job killed")
            self.reset()

    def reset(self) -> None:
        self._require_open()
        self.halted = False
        self._resetting = True
        self._out.append((Lane.REALTIME, b"\x18"))

    def clear(self, token: Any) -> bool:
        """`UNLOCK` ends an ALARM, once no line is unanswered."""
        self._require_ready()
        if self.model.state is not MachineState.ALARM:
            return False
        self._outbox.append(Queued(b"UNLOCK\n", CommandClass.CLEAR, token, Context.ANY))
        return True
