"""g2core's session: every rule of the controller, with no I/O (see session.py).

Every write is decided by the state the board last reported, applied before
the write:
- a client's line is admitted twice: when it arrives, and again at the moment
  it is written. It carries the context it was admitted in (free, in a hold,
  any); if that context is gone by then (a hold began or ended, a job
  started, a lockout began), it fails with a clear error instead of running
  where it was never meant to. Waiting lines are re-checked on every change;
- lines pass the command class table (`classes.py`) in ALARM, SHUTDOWN and
  PANIC; job lines are not written at all then;
- job lines are not written while the job is paused (from its `!` to its
  `~`) nor while the board reports a hold; in-hold lines (`{"gc2":...}`) and
  queries go at once, past the window, through a bounded control lane;
- an exception report stops job lines until a status report says where the
  board is (an `er` may announce an alarm before its status report does);
- after `%` or 0x04 no data line is written until the board shows the flush
  happened: until then its answers to lines read before the flush still
  arrive and are matched; then the rest, which it discarded, are dropped
  from the books and accounted. A `%` is shown by a stop (stat 3/4). A ^D
  (0x04) is shown by its fences: `$stat` written right behind the ^D on the
  data port, which the board reads only after that ^D has thrown away the
  port's unread lines and the kill has run (and on two ports a `{"stat":null}`
  behind the control port's ^D); not by counting `er` 207s, since kills that
  meet merge into one report (docs/protocol.md, "A kill's fence"). Before 101.02
  a ^D is an ALARM that flushes nothing: each line is answered 204, and the
  session clears the ALARM afterwards;
- a lockout announced by an exception report stands until a report shows
  it or a clear succeeds (a board passes through a hold first, or on
  101.02-101.04 never gets there: then the session stops it itself);
- a clear is written on the data port, and only when none of our data lines
  is unanswered: the board runs a `{`-line ahead of waiting G-code, and a
  stale line must not run after the alarm is cleared. For the same reason a
  job's own `{`-line waits for the job's lines before it.

What differs between firmware builds is in g2builds.py, read from the `fb`
the handshake learns.

The handshake (g2core.md section 10): the banner, or after `BANNER_WAIT` on
a link that prints none a version request; the firmware build checked; the
protocol settings; `{home:n}`; a full status report. What it accepts and
sends is in g2handshake.py; its steps are here. Then the heartbeat: a
board silent for `heartbeat` seconds is asked for a report, and one that
does not answer within as long again is gone.
"""

from __future__ import annotations

import re
import time
from collections import deque
from collections.abc import Callable, Iterable
from enum import Enum, auto
from typing import Any

import structlog

from hostd.protocol.classes import CommandClass, admit, classify
from hostd.protocol.commands import (
    MAX_LINE_BYTES,
    InvalidCommand,
    Realtime,
    Refusal,
    encode_clear,
    encode_get,
    encode_in_hold,
    encode_line,
    encode_realtime,
    encode_set,
    validate_line,
)
from hostd.protocol.errors import (
    Busy,
    ControllerError,
    MachineError,
    NotConnected,
    Rejected,
)
from hostd.protocol.g2builds import NEWEST, OVERRIDE_RANGES, Build
from hostd.protocol.g2handshake import (
    BANNER_WAIT,
    OLDEST_BUILD,
    STATUS_KEYS,
    TINYG_BUILDS,
    check_firmware,
    protocol_settings,
)
from hostd.protocol.g2words import G2Words, setting_number
from hostd.protocol.gcode import plain_match
from hostd.protocol.linemode import InFlight, LineModeSender, SenderError
from hostd.protocol.messages import (
    Banner,
    ExceptionReport,
    Notice,
    Response,
    StatusReport,
    Unparseable,
)
from hostd.protocol.parser import parse_line, plain_answer
from hostd.protocol.program import MAX_LINE_NUMBER, NOT_PREFIXED, number_line
from hostd.protocol.relaxed import parse_relaxed
from hostd.protocol.session import SessionBase
from hostd.protocol.states import MachineState
from hostd.protocol.status import LOCKOUT_RAISED_BY, Status, message
from hostd.protocol.stream import Stream
from hostd.protocol.vocabulary import (
    Context,
    Excepted,
    Lane,
    OwnLine,
    Phase,
    Probed,
    Queued,
    Ready,
    Reported,
    StreamEnd,
)

# The handshake's constants live in g2handshake.py and stay importable from here.
__all__ = [
    "BANNER_WAIT",
    "FLUSH_CONFIRM_TIMEOUT",
    "OLDEST_BUILD",
    "STATUS_KEYS",
    "TINYG_BUILDS",
    "G2Session",
]

log = structlog.get_logger(__name__)

FLUSH_CONFIRM_TIMEOUT = 2.0

_NOT_TEXT = frozenset({"not valid UTF-8", "control characters in a text line"})
# Statuses that call a line malformed: for the daemon's own lines, a daemon bug (`syntax`).
_MALFORMED = frozenset(
    {
        Status.INVALID_OR_MALFORMED_COMMAND,
        Status.BAD_NUMBER_FORMAT,
        Status.UNSUPPORTED_TYPE,
        Status.JSON_SYNTAX_ERROR,
        Status.JSON_TOO_MANY_PAIRS,
        Status.VALUE_TYPE_ERROR,
    }
)
_LOCKOUT_REJECTIONS = frozenset(
    {
        Status.COMMAND_REJECTED_BY_ALARM,
        Status.COMMAND_REJECTED_BY_SHUTDOWN,
        Status.COMMAND_REJECTED_BY_PANIC,
    }
)
# States in which the board has run its flush (cycle ended, planner empty).
_FLUSH_CONFIRMED = frozenset({MachineState.PROGRAM_STOP, MachineState.PROGRAM_END})
_RESTING_STATES = frozenset({MachineState.READY, *_FLUSH_CONFIRMED})


class _Own(OwnLine, Enum):
    """What a line of the session's own is for; its answer goes back to that."""

    VERSION = auto()  # {fv:n,fb:n}: a board that printed no banner
    SETTING = auto()  # a protocol setting of the handshake
    HOMED = auto()  # {home:n}, in the handshake and after homing
    FIRST_REPORT = auto()  # the handshake's last step: a full status report
    HEARTBEAT = auto()  # a silent board asked for a report
    QUERY = auto()  # a status report asked for (after an `er`, at a job's end)
    REAPPLY = auto()  # a setting sent again once a lockout ended
    CLEAR = auto()  # the clear that ends the ALARM a 100.x board makes of a ^D
    FENCE = auto()  # `{"stat":null}` behind a ^D on the control port: that ^D was read
    OVERRIDES = auto()  # the override factors, read or written (g2builds.py override_keys)


class G2Session(G2Words, SessionBase):
    """One g2core board's protocol, across the connections of a daemon's life.

    `open()` starts a connection's handshake and `close()` settles
    everything a connection carried; between the two, `receive()` takes each
    line the board prints and the request methods take what clients ask.
    """

    def __init__(
        self,
        machine_id: str,
        *,
        window: int = 4,
        status_interval: float = 0.25,
        heartbeat: float = 2.0,
        handshake_timeout: float = 5.0,
        signal_keys: Iterable[str] = (),
        dual: bool = False,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(machine_id, clock)
        # Two ports (g2core.md section 9): a kill or a flush on the control port flushes
        # only that port's input (xio.cpp flushToCommand), so each is sent on both.
        self.dual = dual
        self.build: Build = NEWEST  # the board's rules (g2builds.py), from its `fb`
        self.status_interval = status_interval
        self.heartbeat = heartbeat
        self.handshake_timeout = handshake_timeout
        self.signal_keys = tuple(signal_keys)
        self.sender = LineModeSender(window)
        self._flush: Realtime | None = None  # QUEUE_FLUSH or JOB_KILL, awaiting its proof
        self._flush_out = False  # the flush's byte has been handed to the engine to write
        self._flush_deadline: float | None = None
        # ^D written whose `er` 207 may still come: a 207 of ours is no new exception.
        # Kills that meet merge into one 207, so this only recognises them; the fence
        # behind each ^D (`_write_fence`) is what shows its flush.
        self._kills_unseen = 0
        self._control_fences = 0  # `_Own.FENCE` lines unanswered (two ports)
        self._kill_alarm = False  # a 100.x ^D written: its `er` 207 is an ALARM of ours
        # A lockout an exception report announced: it stands until a report shows the
        # board in it (2, 12, 13) or a clear succeeds, whatever stat a hold shows meanwhile.
        self._held: MachineState | None = None
        self._alarm_kill_due = False  # 101.05+: the alarm's own job kill (`er` 207) is to come
        self._settings_pending = False  # refused in a lockout: sent again when it ends
        self._lines_in = 0  # lines read and understood this connection (the serial fault's value)
        self._last_rx = 0.0
        # The handshake: its deadlines, what it learnt, the settings still to send.
        self._rebooting = False
        self._banner_deadline: float | None = None
        self._handshake_deadline: float | None = None
        self._identity: float | None = None
        self._to_set: deque[dict[str, Any]] = deque()
        self._heartbeat_deadline: float | None = None  # a heartbeat query is unanswered
        # Where the board last rested (its machine position, or work position), and whether a report
        # since showed it elsewhere or moving: a stop that moved nothing is no underflow.
        self._rest_at: dict[str, float] | None = None
        self._moved = False

    # -- outputs -------------------------------------------------------------

    def next_deadline(self) -> float | None:
        if self._closing_reason is not None:
            return None
        deadline = None  # asked after every step: no list built
        for d in (
            self._banner_deadline,
            self._handshake_deadline,
            self._flush_deadline,
            self._heartbeat_deadline,
        ):
            if d is not None and (deadline is None or d < deadline):
                deadline = d
        if self.phase is Phase.READY and self.heartbeat and self._heartbeat_deadline is None:
            beat = self._last_rx + self.heartbeat
            if deadline is None or beat < deadline:
                deadline = beat
        return deadline

    # -- the connection --------------------------------------------------------

    def open(self, *, rebooting: bool = False) -> None:
        """The link is open: begin the handshake. After 0x18 only the banner will do."""
        now = self.clock()
        self.phase = Phase.HANDSHAKE
        self._closing_reason = None
        self._rebooting = rebooting
        self._identity = None
        self._last_rx = now
        self._handshake_deadline = now + self.handshake_timeout
        # A board on a UART link prints its banner only at boot, not when a host
        # opens the port: if none comes soon, ask for the version instead.
        wait = min(BANNER_WAIT, self.handshake_timeout / 2)
        self._banner_deadline = None if rebooting else now + wait

    def close(self, reason: str, *, restarted: bool = False) -> None:
        """The link is gone: settle every line and request it carried."""
        self.phase = Phase.CLOSED
        self._flush = None
        self._kills_unseen = self._control_fences = 0
        self._kill_alarm = self._alarm_kill_due = False
        self._held = None
        self._banner_deadline = self._handshake_deadline = None
        self._flush_deadline = self._heartbeat_deadline = None
        lost = NotConnected(f"link lost: {reason}")
        for entry in self.sender.clear():
            self._settle_unanswered(entry, lost)
        for waiting in (self._outbox, self._lane):
            while waiting:
                self._settle(waiting.popleft().token, lost)
        self._end_stream_on_close(reason, restarted)
        self._await_report = self._awaiting_rest = False
        self._settings_pending = False
        self._rest_at, self._moved = None, False
        self._to_set.clear()
        self._lines_in = 0
        self._out.clear()
        self.model.reset()

    # -- reading ---------------------------------------------------------------

    def receive(self, line: bytes) -> None:
        """One line the board printed (without its line end)."""
        self._last_rx = self.clock()
        plain = plain_answer(line)
        if plain is not None and plain[2] == b"0":
            # `{"r":{},"f":[1,0,count]}` for the oldest job line, taken in one look: what
            # `_on_response` would do with it (the line is acknowledged), unparsed.
            entry = self.sender.pop_job_answer(int(plain[3]))
            if entry is not None:
                self._lines_in += 1
                if entry.source.acknowledged(entry.file_line):
                    self._check_stream_complete()
                return
        msg = parse_line(line)
        if isinstance(msg, Response):
            self._on_response(msg)
        elif isinstance(msg, StatusReport):
            self._on_status(msg.fields)
        elif isinstance(msg, ExceptionReport):
            self._on_exception(msg)
        elif isinstance(msg, Banner):
            self._on_banner(msg)
        elif isinstance(msg, Unparseable):
            self._job_log().warning("unparseable controller output", reason=msg.reason, raw=msg.raw)
            kind = "serial" if msg.reason in _NOT_TEXT else "lexical"
            self._detected(kind, self._lines_in, f"{msg.reason}: {msg.raw[:60]!r}")
            return
        elif isinstance(msg, Notice) and isinstance(msg.fields.get("prb"), dict):
            self._on_probe(msg.fields["prb"])
        else:
            self._log.debug("controller said", message=type(msg).__name__)
        self._lines_in += 1

    def receive_plain(self, lines: list[bytes], start: int) -> int:
        """`receive`'s first branch for a run of lines: plain answers (`{"r":{"n":N},
        "f":[1,0,C]}`) to the job's oldest lines, booked together. Not at the job's
        end (its input ended, or a refused line's turn came: each answer then checks
        whether the job is complete), nor while a control line waits for its answer."""
        stream = self._steady_stream()
        if stream is None:
            return start
        index, answered = self.sender.pop_job_answers(lines, start, stream)
        if answered:
            self._last_rx = self.clock()
            self._lines_in += len(answered)
            stream.acknowledged_run(answered)
        return index

    def _on_response(self, response: Response) -> None:
        if response.count < 2:
            # No line of ours is answered with fewer than 2 (a data line of L >= 1
            # bytes gets L + 1): a report shaped as an answer (report.cpp startup
            # messages, status 15; cycle_homing.cpp's failed homing, status 240).
            self._unbooked(response)
            return
        if self.sender.fences:
            fenced = self.sender.fence_answered(response)
            if fenced is not None:
                for entry in fenced[1]:  # thrown away unread by the ^D ahead of the fence
                    self._settle_unanswered(entry, _discarded(Realtime.JOB_KILL))
                self._kill_fenced()
                return
        try:
            entry, skipped = self.sender.answered(response)
        except SenderError:
            self._job_log().warning("answer with no line waiting", raw=response.raw)
            self._detected("lexical", None, f"an answer with no line waiting: {response.raw!r}")
            return
        for lost in skipped:
            self._job_log().warning("the controller never answered a line", line=lost.line)
            self._settle_unanswered(lost, ControllerError(0, "the controller never answered"))
            if lost.file_line is not None:
                self._fail_job_line(lost.source, lost, "got no answer from the controller")
        if entry.own and response.status in _MALFORMED:
            # The board calls a line the daemon wrote malformed: a daemon bug.
            line = entry.line.rstrip(b"\n").decode(errors="replace")
            self._detected("syntax", line, f"{line!r} refused: {message(response.status)}")
        report = response.status_report
        if report is not None:
            self._on_status(report)
        if response.ok and (entry.line == _CLEAR or (self._held and _clears(entry.line))):
            self._cleared()
        elif response.status in _LOCKOUT_REJECTIONS:
            self._refused_in_lockout(Status(response.status))
        source = entry.source
        if entry.file_line is not None:
            self._on_job_answer(source, entry, response)
        elif isinstance(source, _Own):
            self._own_answered(source, entry, response)
        else:
            self._settle(source, response)

    def _unbooked(self, response: Response) -> None:
        """An `{r}` that answers no line: startup chatter is noted; anything else is an event."""
        if response.status == Status.INITIALIZING:
            self._log.info("controller initializing", msg=response.body.get("msg"))
            return
        body_msg = response.body.get("msg")
        msg = body_msg if isinstance(body_msg, str) else ""
        fields = {"st": response.status, "msg": msg}
        stream = self.stream
        if response.status and stream is not None and not stream.done:
            # cycle_homing.cpp answers the G28.2 itself with 0 and reports its failure
            # apart; the board would run the moves after it from an unknown position.
            what = f"controller reported {response.status}: {msg or message(response.status)}"
            self._end_stream(stream, StreamEnd.FAILED, ControllerError.code, what)
            self._write_realtime(Realtime.JOB_KILL)
        self._on_exception(ExceptionReport(response.status, msg, fields, response.raw))

    def _fail_job_line(self, stream: Stream, entry: InFlight, what: str) -> None:
        """A job line went wrong on the board: the job fails, and what follows it must not run."""
        if stream.done:
            return
        what = f"line {entry.file_line}: {what}"
        self._end_stream(stream, StreamEnd.FAILED, ControllerError.code, what)
        self._write_realtime(Realtime.JOB_KILL)

    def _job_line_ok(self, stream: Stream, entry: InFlight) -> None:
        stream.acknowledged(entry.file_line)
        self._check_stream_complete()

    def _on_job_answer(self, stream: Stream, entry: InFlight, response: Response) -> None:
        if response.ok:
            self._job_line_ok(stream, entry)
            return
        status = response.status
        if stream.done and self._kill_alarm and status == Status.COMMAND_REJECTED_BY_ALARM:
            # A 100.x ^D is an ALARM that flushes nothing: each line it caught is read and
            # refused (100.26 controller.cpp:259). None ran: the kill discarded it.
            stream.discarded += 1
            return
        stream.rejected += 1
        if stream.done:
            return  # already ended (an alarm, a cancel): this answer is accounted, no more
        text = message(status)
        if status in _LOCKOUT_REJECTIONS:
            self._end_stream(stream, StreamEnd.FAILED, status, text)
        else:
            self._end_stream(
                stream,
                StreamEnd.FAILED,
                ControllerError.code,
                f"line {entry.file_line}: controller answered {status}: {text}",
            )
            # Lines already sent behind the bad one must not run: kill the job on the board.
            self._write_realtime(Realtime.JOB_KILL)

    def _on_status(self, fields: dict[str, Any]) -> None:
        before = self.model.state
        changed = self.model.apply_status(fields)
        held = self._held
        if held is not None and "stat" in fields:
            state = self.model.state
            if state is not None and state.is_lockout:
                self._held = None  # the board shows the lockout: its reports rule again
                self._alarm_kill_due = False  # its own kill, if any, came before (:354)
            else:
                # 101.05+ passes through a hold (stat 6/5) before ALARM; 101.02-101.04
                # never enter it: the announced lockout stands until a clear.
                self.model.state = held
                changed = None
        if "stat" in fields:
            self._await_report = False
            self._confirm_flush()
            if self._awaiting_rest:
                self._check_stream_complete(reported=True)
        self._track_motion()
        if changed is not None:
            self._on_state(changed, before)
        if self._moved and self.model.state in _RESTING_STATES:
            here = self.model.machine_position or self.model.position
            self._rest_at, self._moved = dict(here), False  # at rest: moves count from here
        self._track_executed()
        self._events.append(Reported(fields, self.model.snapshot()))

    def _track_motion(self) -> None:
        """Whether the board moved since it last rested: a report away from there (its
        machine position, or its work position where it reports no machine position),
        or with a speed. A run with nothing to move starts and ends a cycle where it
        stood: g2core drops a zero-length move and ends the cycle it started for it
        (canonical_machine.cpp:1204-1211, 1360-1367), and a tool change, a dwell or an
        M-code moves no axis."""
        model = self.model
        here = model.machine_position or model.position
        if self._rest_at is None or (model.velocity or 0.0) > 0.0 or here != self._rest_at:
            self._moved = True

    def _track_executed(self) -> None:
        """`line` is the runtime's N while the board moves (stat 5), and only then.

        canonical_machine.cpp: `line` reads the ACTIVE_MODEL, which is the runtime
        (the block being executed) while motion runs, and the parser's model (the last
        line *read*, possibly far ahead in the planner) once motion stops, in a hold
        too. So only a report showing RUN says which line executes.
        """
        stream = self.stream
        line = self.model.line
        if stream is not None and not stream.done and line and self.model.state is MachineState.RUN:
            stream.executing(line)

    def _on_exception(self, report: ExceptionReport) -> None:
        if report.status == Status.KILL_JOB and self._on_kill_report(report):
            return
        self.model.apply_exception(report)
        self._job_log().warning("controller exception", status=report.status, msg=report.message)
        self._events.append(Excepted(report.fields))
        raised = LOCKOUT_RAISED_BY.get(report.status or -1)
        if report.status == Status.ENCODER_ASSERTION_FAILURE and (
            not self.build.alarm_holds_first or "assertions" in (report.message or "")
        ):
            # encoder.cpp:64 panics with 92 on every build; only edge-preview's
            # kinematics_four_cable.h:684 alarms with it ("encoder stopped returning values").
            raised = "PANIC"
        if report.status == Status.JSON_OUTPUT_TOO_LONG:
            # json_parser.cpp sends this instead of the answer of the line it is on.
            self._answer_too_long()
        if raised is not None:
            self._announced(MachineState[raised])
        # Nothing of ours is written until a status report says where the board is.
        self._await_report = True
        self._query_status()

    def _announced(self, lockout: MachineState) -> None:
        """An exception report of the alarm, shutdown or panic class: locked out from now.

        How the board gets there depends on its build (g2builds.py): at once
        before 101.02; through a hold, its own job kill and `er` 207 from 101.05;
        never on 101.02-101.04, whose board would run the next line it reads, so
        hostd stops it itself (^D) and keeps its own lockout until a clear.
        """
        build = self.build
        stop = False
        if lockout is not MachineState.PANIC and self.model.state is not lockout:
            if build.alarm_holds_first and not self.model.hold and not self._kills_unseen:
                # Its hold ends in a job kill of its own; none when a hold (ours, or a
                # kill's) is already under way: cm_request_feedhold ignores it then.
                self._alarm_kill_due = True
            stop = not build.alarm_is_state
        self._held = lockout
        self.model.state = lockout
        self._on_state(lockout)  # the job ends failed with the lockout's code first
        if stop:
            self._write_realtime(Realtime.JOB_KILL)

    def _on_kill_report(self, report: ExceptionReport) -> bool:
        """An `er` 207; True when it is accounted here and is no new exception.

        - From 101.05 an alarm's hold ends in a job kill of the board's own: its
          207 follows the alarm's report and is a consequence of it (it must not
          replace the alarm's reason, nor stand for a kill of ours).
        - In a lockout a 207 tells nothing new either: the reason stays.
        - Before 101.02 our ^D is an ALARM ("EOT Received"): a lockout of ours,
          which we clear once its lines are answered.
        - Otherwise it may be one of our ^D's (or several that merged: one
          `_run_job_kill` clears every request made before it, cycle_feedhold.cpp
          :523,553). It is told as an exception; the fence behind the ^D, not
          this report, shows what the kill discarded.
        """
        if self._alarm_kill_due:
            self._alarm_kill_due = False
            self._job_log().info("the alarm's own job kill", msg=report.message)
            return True
        locked = self._held is not None or (self.model.state and self.model.state.is_lockout)
        if self.build.kill_alarms and not locked:
            # Whoever wrote the ^D, the board is in ALARM now (cm_alarm, 100.26).
            self.model.apply_exception(report)
            self._events.append(Excepted(report.fields))
            self._held = MachineState.ALARM
            self.model.state = MachineState.ALARM
            self._on_state(MachineState.ALARM)
            if self._kill_alarm:  # ours: cleared once the lines it caught are answered
                clear = Queued(encode_clear(), CommandClass.CLEAR, _Own.CLEAR, Context.OWN)
                self._outbox.append(clear)
            self._await_report = True
            self._query_status()
            return True
        if self._kills_unseen > 0:
            self._kills_unseen -= 1
            if self._held is None and not (self.model.state and self.model.state.is_lockout):
                self.model.apply_exception(report)
                self._events.append(Excepted(report.fields))
            return True
        if locked:
            self._job_log().info("a job kill in a lockout", msg=report.message)
            return True
        return False

    def _cleared(self) -> None:
        """A clear was answered OK: a lockout of ours ends; a report says where the board is.

        Not while a 101.05+ alarm's hold still runs: `cm_clear` finds no ALARM yet
        and does nothing, and the board enters ALARM once held.
        """
        if not self._alarm_kill_due:
            self._held = None
        self._kill_alarm = False
        self._await_report = True
        self._query_status()

    def _refused_in_lockout(self, status: Status) -> None:
        """A 204/205/206 answer says the board is locked out, even before any report does."""
        state = self.model.state
        lockout = _LOCKOUT_OF[status]
        if state is lockout or self._held is not None:
            return
        if state is not None and state.is_lockout and lockout is not MachineState.PANIC:
            return
        self.model.state = lockout
        self._on_state(lockout, state)

    def _answer_too_long(self) -> None:
        """The answer to the control line being run did not fit: that line fails with 113."""
        entry = self.sender.oldest_control()
        if entry is None:
            return
        error = ControllerError(Status.JSON_OUTPUT_TOO_LONG, message(Status.JSON_OUTPUT_TOO_LONG))
        self._settle_unanswered(entry, error)
        if entry.file_line is not None:
            self._fail_job_line(entry.source, entry, "its answer was too long for the controller")

    def _on_probe(self, report: dict[str, Any]) -> None:
        """A probe cycle's result (cycle_probing.cpp `_send_probe_report`): kept and told."""
        probe = self.model.apply_probe(report)
        self._job_log().info("probe", ok=probe["ok"], position=probe["position"])
        self._events.append(Probed(report, probe))

    def _on_banner(self, banner: Banner) -> None:
        if self.phase is Phase.HANDSHAKE:
            if (self._identity is None and self._banner_deadline is not None) or self._rebooting:
                self._banner_deadline = None
                self._rebooting = False
                self._identified(banner.fb)
            return  # a banner while we already asked for the version: that answer decides
        # SYSTEM READY mid-session: the board restarted under us.
        self._closing("controller restarted (unexpected SYSTEM READY)")

    def _on_state(self, state: MachineState, before: MachineState | None = None) -> None:
        self._job_log().info("controller state", state=state.name)
        if before is MachineState.HOMING:
            self._ask_own(encode_get("home"), _Own.HOMED)  # a homing cycle ended, done or failed
        if state is MachineState.PROGRAM_END and self.model.overrides is not None:
            # A program end puts the feed and traverse factors back to 1.0, the spindle's
            # untouched (_exec_program_finalize calls cm_reset_overrides: edge-preview
            # canonical_machine.cpp:1436-1442, 1632; 100.26 :1617-1624).
            self.model.overrides = {**self.model.overrides, "feed": 100.0, "rapid": 100.0}
        stream = self.stream
        if state is MachineState.RUN and stream is not None:
            stream.program_pause_sent = False
        elif (
            state in _FLUSH_CONFIRMED
            and stream is not None
            and not stream.done
            and not stream.program_pause_sent
            and self._flush is None
            and not stream.paused  # a pause the board ignored (nothing moving) is no underflow
            and not self._await_report  # the host held the lines back: no starving
            and not self.model.hold  # a hold at rest (101.05+) is no starving either
            and stream.lines_on_host()  # but a `{`-line, which waits on purpose
            and self._moved  # a run that moved nothing starved nothing (at rest, M6, G4)
        ):
            # The board ran out of moves while the job still had lines on the host:
            # reported with the file line it stopped after (behaviour.md, faults).
            line = stream.last_acked_line
            self._detected("underflow", line, f"the controller stopped after file line {line}")
        if state.is_lockout:
            self._drain_for_lockout(state, message)
        elif self._settings_pending and self.phase is Phase.READY:
            self._settings_pending = False
            for setting in protocol_settings(self.status_interval, self.signal_keys):
                self._ask_own(encode_set(setting), _Own.REAPPLY)
        self._recheck_waiting()

    # -- timers ----------------------------------------------------------------

    def tick(self) -> None:
        """A deadline passed (or the engine woke early: nothing is due then)."""
        now = self.clock()
        if self._closing_reason is not None:
            return
        if self._handshake_deadline is not None and now >= self._handshake_deadline:
            self._handshake_timed_out()
            return
        if self._banner_deadline is not None and now >= self._banner_deadline:
            self._banner_deadline = None
            self._ask_own(encode_get("fv", "fb"), _Own.VERSION)
        if self._flush_deadline is not None and now >= self._flush_deadline:
            # A `%` outside a hold flushes nothing: its lines will be answered as usual.
            # A kill's fence still unread (the board does not read its data port): data
            # lines may go again, behind it; its answer still settles the lines before it.
            self._log.warning("flush not confirmed by the controller")
            self._flush = self._flush_deadline = None
            self._kills_unseen = 0
        if self.phase is not Phase.READY or not self.heartbeat:
            return
        if self._heartbeat_deadline is not None:
            if now >= self._heartbeat_deadline:
                silent = 2 * self.heartbeat
                self._closing(f"controller silent for {silent:g} s (no answer to a status request)")
        elif now >= self._last_rx + self.heartbeat:
            # A silent board is asked for a report; one that stays silent is gone.
            self._heartbeat_deadline = now + self.heartbeat
            self._ask_own(encode_get("sr"), _Own.HEARTBEAT)

    # -- the handshake ---------------------------------------------------------

    def _identified(self, fb: float | None) -> None:
        try:
            check_firmware(fb)
        except NotConnected as exc:
            self._closing(exc.message)
            return
        self._identity = fb
        assert fb is not None  # check_firmware refuses a board that did not say
        self.build = Build(fb)
        self._to_set = deque(protocol_settings(self.status_interval, self.signal_keys))
        self._next_setting()

    def _next_setting(self) -> None:
        if self._to_set:
            self._ask_own(encode_set(self._to_set[0]), _Own.SETTING)
        else:
            self._read_overrides()  # answered before the report that makes the session ready
            self._ask_own(encode_get("home"), _Own.HOMED)
            self._ask_own(encode_get("sr"), _Own.FIRST_REPORT)

    def _own_answered(self, own: _Own, entry: InFlight, response: Response) -> None:
        if own is _Own.VERSION and self.phase is Phase.HANDSHAKE:
            self._identified(setting_number(response.body.get("fb")))
        elif own is _Own.SETTING and self._to_set:
            setting = self._to_set.popleft()
            if response.status in _LOCKOUT_REJECTIONS:
                # A board in ALARM refuses every SET: sent again once it is cleared.
                self._settings_pending = True
            elif not response.ok:
                status = response.status
                self._closing(f"controller refused {setting}: {status} ({message(status)})")
                return
            self._next_setting()
        elif own is _Own.HOMED and response.ok:
            self.model.apply_status({"home": response.body.get("home")})
        elif own is _Own.FIRST_REPORT and self.phase is Phase.HANDSHAKE:
            self.phase = Phase.READY
            self._handshake_deadline = None
            self._events.append(Ready())
        elif own is _Own.OVERRIDES:
            self._overrides_answered(response)
        elif own is _Own.HEARTBEAT:
            self._heartbeat_deadline = None
        elif own is _Own.FENCE:
            self._control_fences = max(0, self._control_fences - 1)
            self._kill_fenced()
        elif own is _Own.CLEAR and not response.ok:
            self._log.error("controller refused the clear after a kill", status=response.status)
        elif own is _Own.REAPPLY and not response.ok:
            self._log.error("controller refused a setting", setting=entry.line)

    def _handshake_timed_out(self) -> None:
        step = (
            "answer to its settings"
            if self._identity is not None
            else "SYSTEM READY banner"
            if self._banner_deadline is None and self._rebooting
            else "SYSTEM READY banner, nor an answer to a version request,"
        )
        timeout = self.handshake_timeout
        self._closing(f"no {step} from the controller within {timeout:g} s")

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
        if (
            stream is None
            or stream.done
            or stream.paused
            or self._await_report
            or (state is not None and (state.is_lockout or state is MachineState.HOLD))
            or self.model.hold  # a hold at rest (101.05+) shows in `hold` alone
        ):
            return
        out = self._out
        data = Lane.DATA
        if self.fast_path:
            # The steady state: the plain lines ahead that the window has room for, taken
            # and booked together; the loop below goes on from the first line it left.
            room = sender.window - sender.data_in_flight
            if room > 0:
                taken = stream.take_run(room)
                if taken:
                    sender.book_run(taken)
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

    def _book(self, encoded: bytes, source: Any, lane: Lane, *, own: bool = False) -> None:
        """Write one line and put it on the books; an urgent one may pass its budget."""
        if self.halted:
            self._settle(source, self._write_refused())
            return
        try:
            self.sender.sent(InFlight(encoded, source, None, own), urgent=own)
        except SenderError as exc:
            self.halt(str(exc))
            self._settle(source, self._write_refused())
            return
        self._out.append((lane, encoded))

    def _ask_own(self, encoded: bytes, purpose: _Own) -> None:
        """A line of the session's own, ahead of anything queued."""
        if self.phase is not Phase.CLOSED:
            self._book(encoded, purpose, Lane.CONTROL, own=True)

    def _write_realtime(self, command: Realtime) -> None:
        self._out.append((Lane.REALTIME, encode_realtime(command)))
        build = self.build
        if command is Realtime.JOB_KILL and build.kill_alarms:
            # Before 101.02 ^D is an ALARM and flushes nothing: every line in flight is
            # read and answered 204, and those answers settle it (g2builds.py).
            self._kill_alarm = True
            if self.stream is not None:
                self._end_stream(self.stream, StreamEnd.CANCELLED, None, "job killed")
            return
        if command is Realtime.JOB_KILL:
            self._kills_unseen += 1
            if self.dual:  # the data port's lines too: the ^D flushes its own port only
                self._out.append((Lane.DATA, encode_realtime(command)))
                self._kills_unseen += 1
            self._write_fence()
        elif (
            command is Realtime.QUEUE_FLUSH and self.dual and not build.flush_reads_every_data_port
        ):
            # Before 101.05 a `%` flushes its own port alone; after a `!` on the same
            # port it is a flush even at rest (xio.cpp `_last_control_was_feedhold`).
            self._out.append((Lane.DATA, encode_realtime(Realtime.FEEDHOLD)))
            self._out.append((Lane.DATA, encode_realtime(command)))
        if command in (Realtime.QUEUE_FLUSH, Realtime.JOB_KILL):
            # Whether the board flushes depends on its state *now*, which the last
            # report may not show yet: expect a flush, and let the confirmation
            # (or its absence) decide what happened to the lines in flight.
            self._begin_flush(command)

    def _write_fence(self) -> None:
        """The fences behind a ^D (docs/protocol.md, "A kill's fence").

        On the data port (the only port, or the second) `$stat`, a data line: the
        board reads that port's controls first, each in turn, and its data lines in
        order (xio.cpp:643-827); the ^D it reads throws away the data lines it had
        scanned, those written before the ^D (controller.cpp:282, xio.cpp:984-1017),
        in any state; and no data line is read while a hold is on (cycle_feedhold.cpp
        :325), so not before the kill's own hold has ended in its kill. When `$stat`
        is answered, each data line written before it was answered already or is
        gone, and the kill has run. A GET of a read-only status key (`_FENCE_KEYS`)
        is answered in any state; as `$stat` it takes a form no other line does (a
        client's query goes as strict JSON, `_as_json_query`, and a SET of a
        read-only key is answered with an error).

        On two ports also `{"stat":null}` behind the control port's ^D, in that
        port's order: answered, that ^D was read, so no kill of hostd's can reach
        the board later and stop what runs then.
        """
        if self.halted:
            return  # nothing is written: the link is being torn down
        # A fence still unanswered may be thrown away unread by this ^D: each asks for
        # another key, so that its answer says which it is (LineModeSender.fence).
        in_use = self.sender.fence_keys()
        key = next((k for k in _FENCE_KEYS if frozenset((k,)) not in in_use), None)
        if key is None:
            # As many kills at once as keys (a board that read none of their fences):
            # no fence. The timeout ends the wait; lines still booked stay booked until
            # an earlier fence, if any is still read, settles them.
            self._log.warning("no fence for a kill: too many kills at once", kills=len(in_use))
        else:
            fence = f"${key}\n".encode("ascii")
            self.sender.fence(InFlight(fence, _Own.FENCE, None, True), frozenset((key,)))
            self._out.append((Lane.DATA, fence))
        if self.dual:
            self._control_fences += 1
            self._book(encode_get("stat"), _Own.FENCE, Lane.CONTROL, own=True)

    def _kill_fenced(self) -> None:
        """A fence was answered: with the last of every kill's, the kills' wait ends.

        Every ^D was read by then and every kill it asked for has run: its `er`
        207, if any, came first (`_run_job_kill` runs before the next line is read
        at rest, and ends the hold the data port waits for in a cycle)."""
        if self.sender.fences or self._control_fences:
            return
        self._kills_unseen = 0
        if self._flush is Realtime.JOB_KILL:
            self._flush = self._flush_deadline = None

    def _query_status(self) -> None:
        """Ask for a full status report, ahead of anything queued."""
        self._ask_own(encode_get("sr"), _Own.QUERY)

    # -- flushes ---------------------------------------------------------------

    def _begin_flush(self, kind: Realtime) -> None:
        self._flush = kind
        self._flush_out = False
        self._flush_deadline = self.clock() + FLUSH_CONFIRM_TIMEOUT
        if self.stream is not None and not self.stream.done:
            reason = "job killed" if kind is Realtime.JOB_KILL else "queue flushed"
            self._end_stream(self.stream, StreamEnd.CANCELLED, None, reason)

    def _confirm_flush(self) -> None:
        """A queue flush is shown by a stop (stat 3 or 4), read after the `%` went out (a
        report read before then, in the batch that decided the flush, says nothing of
        it): the data lines the board held are dropped from the books. A job kill is
        shown by its fence (`_fence_answered`), not here.
        """
        if self._flush is not Realtime.QUEUE_FLUSH or not (
            self._flush_out and self.model.state in _FLUSH_CONFIRMED
        ):
            return
        self._flush = self._flush_deadline = None
        self._kills_unseen = 0
        for entry in self.sender.dropped():
            self._settle_unanswered(entry, _discarded(Realtime.QUEUE_FLUSH))

    def _settle_unanswered(self, entry: InFlight, error: MachineError) -> None:
        source = entry.source
        if entry.file_line is not None:
            source.discarded += 1
        elif isinstance(source, _Own):
            if source is _Own.HEARTBEAT:
                self._heartbeat_deadline = None  # it was read: the board lives
        else:
            self._settle(source, error)

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

    def _admit_action(self, text: str, cls: CommandClass, token: Any) -> None:
        """An action line: in a hold, run inside it at once; free, under the window; else busy."""
        context = self._context()
        if context is Context.JOB:
            pausing = self.stream is not None and self.stream.paused
            raise Busy(
                f"{self.id}: the job is still entering its hold; send again once it holds"
                if pausing
                else f"{self.id} is running {'a job' if self._job_running() else 'an operation'}"
            )
        if context is Context.FREE:
            self._outbox.append(Queued(encode_line(text), cls, token, context))
            return
        if text.startswith("$"):
            # A text line is data: the board would keep it until the hold ends.
            raise Busy(f"{self.id} is in a hold: send settings as JSON ({{key:value}})")
        if _is_gcode(text) and not self.build.in_hold_gcode:
            raise Busy(
                f"{self.id} is in a hold, and its firmware (build {self.build.fb:g}) runs no "
                "G-code inside one (no gc2 before 101.02): resume or cancel first"
            )
        encoded = encode_in_hold(text) if _is_gcode(text) else encode_line(text)
        self._lane.append(Queued(encoded, cls, token, context))

    def _realtime(self, command: Realtime) -> None:
        self._write_realtime(command)

    def override(
        self, feed: int | None = None, rapid: int | None = None, spindle: int | None = None
    ) -> None:
        """The override factors as settings (`{"fro":1.2}`), in any state but a lockout.

        A `{`-line of the session's own on the control lane: the board runs it on
        arrival, ahead of queued G-code, so it acts mid-job; the factor applies to the
        blocks planned after it (edge-preview plan_zoid.cpp:145-148). Where the build
        has a writable enable, it is written on with the factor (100.26's are off at
        start). The answer's values become the model's overrides.
        """
        self._require_ready()
        self.admit_action()  # a board in a lockout refuses every SET: 204/205/206 here
        asked = {"feed": feed, "rapid": rapid, "spindle": spindle}
        keys, enables = self.build.override_keys, self.build.override_enables
        values: dict[str, Any] = {}
        for what, percent in asked.items():
            if percent is None:
                continue
            low, high = OVERRIDE_RANGES[what]
            if not low <= percent <= high:
                raise InvalidCommand(
                    Refusal.BAD_NUMBER,
                    f"a g2core {what} override is {low} to {high} percent, not {percent}",
                )
            if what in enables:
                values[enables[what]] = 1
            values[keys[what]] = round(percent / 100.0, 3)
        self._ask_own(encode_set(values), _Own.OVERRIDES)

    def _read_overrides(self) -> None:
        self._ask_own(encode_get(*self.build.override_keys.values()), _Own.OVERRIDES)

    def _overrides_answered(self, response: Response) -> None:
        """The factors the board answered with (what it stored), as percentages."""
        if not response.ok:
            self._log.warning("override settings refused", status=response.status)
        now = dict(self.model.overrides or {})
        for what, key in self.build.override_keys.items():
            value = response.body.get(key)
            if isinstance(value, int | float) and not isinstance(value, bool):
                now[what] = round(float(value) * 100.0, 1)
        if now:
            self.model.overrides = now
        self.model.override_reports += 1
        self.override_answers += 1  # the answer is what the board stored: no asking again

    def reset(self) -> None:
        """0x18: the board reboots; so do the session's books when it comes back."""
        self._require_open()
        self._write_realtime(Realtime.RESET)
        self.halted = False

    def clear(self, token: Any) -> bool:
        """`{clear:n}` for ALARM or SHUTDOWN, once no data line of ours is unanswered.

        False if there is nothing to clear; PANIC is refused (only a reset leaves it).
        """
        self._require_ready()
        state = self.model.state
        if state is MachineState.PANIC:
            raise Rejected(Status.COMMAND_REJECTED_BY_PANIC, "PANIC is left only by a reset")
        if state not in (MachineState.ALARM, MachineState.SHUTDOWN):
            return False
        self._outbox.append(Queued(encode_clear(), CommandClass.CLEAR, token, Context.OWN))
        return True

    def _admit(self, cls: CommandClass, state: MachineState | None) -> int | None:
        return admit(cls, state)

    def out_of_hold(self) -> bool:
        """Also not while `hold` shows a hold that `stat` does not (a `!` at rest, 101.05+)."""
        return super().out_of_hold() and not self.model.hold

    def _context(self) -> Context:
        """A board that holds is in a hold, whatever its stat says (a `!` at rest, 101.05+)."""
        state = self.model.state
        if self.model.hold and not (state and state.is_lockout):
            return Context.HOLD
        return super()._context()

    def data_to_send(self) -> list[tuple[Lane, bytes]]:
        out = super().data_to_send()
        if self._flush is not None:
            self._flush_out = True  # from now on a report may be the flush's proof
        return out

    def _stop_board(self) -> None:
        """A fault's stop: feedhold, then flush what the board holds."""
        self._write_realtime(Realtime.FEEDHOLD)
        self._write_realtime(Realtime.QUEUE_FLUSH)

    def flushing(self) -> bool:
        return self._flush is not None

    def status_traffic(self, line: bytes, written: bool) -> bool:
        """The session's `{"sr":null}` poll, its answer `{"r":{"sr":{...}},...}`, and the
        `{"sr":{...}}` reports the board sends on its own (g2core/report.cpp
        sr_status_report_callback)."""
        if written:
            return _STATUS_POLL(line.strip()) is not None
        return line.startswith((b'{"sr":', b'{"r":{"sr":'))

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

    def no_data_in_flight(self) -> bool:
        return not self.sender.data_in_flight

    def unanswered(self) -> int:
        return len(self.sender)


_CLEAR = encode_clear()
# `{"sr":null}` as the session writes it, or as an operator may (`{sr:n}`, `{"sr":""}`).
_STATUS_POLL = re.compile(rb'\{\s*"?sr"?\s*:\s*(?:n|null|"")\s*\}', re.IGNORECASE).fullmatch
# A kill's fence on the data port (`_write_fence`): `$<key>`, a text-mode GET answered
# in JSON (`{"r":{"stat":N},"f":[1,0,6]}`: text_parser.cpp:84-96; `__TEXT_MODE` is on,
# g2core.h:42) of read-only status keys, another for each fence unanswered at once
# (edge-preview canonical_machine.cpp:2409-2420, :2510; 101.03 config_app.cpp:117-153).
_FENCE_KEYS = ("stat", "line", "unit", "vel", "feed", "posx", "posy", "posz")
_LOCKOUT_OF = {
    Status.COMMAND_REJECTED_BY_ALARM: MachineState.ALARM,
    Status.COMMAND_REJECTED_BY_SHUTDOWN: MachineState.SHUTDOWN,
    Status.COMMAND_REJECTED_BY_PANIC: MachineState.PANIC,
}


def _clears(encoded: bytes) -> bool:
    """A clear in another form (`$clear`, `M30`...): on 101.02-101.04 the board, never in
    ALARM, runs it as a plain line, and its OK ends the lockout hostd kept."""
    cls = classify(encoded.decode("latin-1").strip())
    return cls is CommandClass.CLEAR or cls is CommandClass.PROGRAM_END


def _lane_of(encoded: bytes) -> Lane:
    return Lane.CONTROL if encoded.startswith(b"{") else Lane.DATA


def _discarded(kind: Realtime) -> MachineError:
    status = Status.KILL_JOB if kind is Realtime.JOB_KILL else Status.NOOP
    what = "job kill" if kind is Realtime.JOB_KILL else "queue flush"
    return ControllerError(int(status), f"discarded by the controller's {what} before it ran")


def _is_gcode(text: str) -> bool:
    return not text.startswith(("{", "$", "?"))


def _as_json_query(text: str) -> bytes:
    """Every query as a strict JSON GET, which the board runs at once on any port."""
    if text == "?":
        return encode_get("sr")
    if text.startswith("$"):
        return encode_get(text[1:].strip().lower())
    obj = parse_relaxed(text)
    return encode_get(*obj) if obj else encode_line(text)
