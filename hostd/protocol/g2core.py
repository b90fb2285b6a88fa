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

The handshake and the heartbeat are in g2connection.py.

`G2Session` is one class written in layers, a file each. A layer calls only
itself, the layers below it and `SessionBase` (session.py), and none overrides
another:

    g2core.py        G2Session     reading: each line the board prints, and
                                   the answers matched to the lines they answer
    g2connection.py  G2Connection  open, the handshake's steps, the heartbeat,
                                   close; the answers to the session's own lines
    g2lockouts.py    G2Lockouts    ALARM, SHUTDOWN, PANIC: announced, shown,
                                   cleared; an `er` 207
    g2status.py      G2Status      status reports and the state they show;
                                   the override factors
    g2kills.py       G2Kills       realtime controls; kills and flushes, and
                                   their proof (a kill's fences)
    g2flow.py        G2Flow        which line is written when: admission,
                                   the lanes, the window, the job's lines
    g2holds.py       G2Holds       a hold: what runs inside one
    g2books.py       G2Books       the state, declared once; the lines written
                                   and not yet answered

Below them all, g2words.py's `G2Words`: the operator's words on g2core (on
words.py's `Words`, which every dialect's words build on).
Method lookups through the layers are cached per class by Python, so the
layers cost a line nothing.
"""

from __future__ import annotations

import structlog

from hostd.protocol.commands import Realtime
from hostd.protocol.errors import ControllerError
from hostd.protocol.g2books import _Own
from hostd.protocol.g2connection import G2Connection
from hostd.protocol.g2kills import _discarded
from hostd.protocol.g2lockouts import _CLEAR, _LOCKOUT_REJECTIONS, _clears
from hostd.protocol.linemode import InFlight, SenderError
from hostd.protocol.messages import (
    Banner,
    ExceptionReport,
    Notice,
    Response,
    StatusReport,
    Unparseable,
)
from hostd.protocol.parser import parse_line, plain_answer
from hostd.protocol.states import MachineState
from hostd.protocol.status import LOCKOUT_RAISED_BY, Status, message
from hostd.protocol.stream import Stream
from hostd.protocol.vocabulary import Excepted, StreamEnd

log = structlog.get_logger(__name__)

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


class G2Session(G2Connection):
    """One g2core board's protocol, across the connections of a daemon's life.

    `open()` starts a connection's handshake and `close()` settles
    everything a connection carried; between the two, `receive()` takes each
    line the board prints and the request methods take what clients ask.
    """

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

    def _take_answers(
        self, lines: list[bytes], start: int, stream: Stream, *, whole: bool = False
    ) -> int:
        """`receive`'s first branch for a run of lines: plain answers (`{"r":{"n":N},
        "f":[1,0,C]}`) to the job's oldest lines, booked together. Not while a control
        line waits for its answer (`pop_job_answers`)."""
        index, answered = self.sender.pop_job_answers(lines, start, stream, whole=whole)
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
            self._on_status(report, requested=True)
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

    def _answer_too_long(self) -> None:
        """The answer to the control line being run did not fit: that line fails with 113."""
        entry = self.sender.oldest_control()
        if entry is None:
            return
        error = ControllerError(Status.JSON_OUTPUT_TOO_LONG, message(Status.JSON_OUTPUT_TOO_LONG))
        self._settle_unanswered(entry, error)
        if entry.file_line is not None:
            self._fail_job_line(entry.source, entry, "its answer was too long for the controller")
