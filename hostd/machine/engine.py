"""One machine's engine: its link, the handshake, and every byte written to the board.

`serve()` owns the connection for the life of the daemon: it opens the link
when asked (or at once with `auto_connect`), runs one session (a TaskGroup:
the reader and the poller) until the link is lost or a disconnect is asked,
tears it down as one, and reconnects with back-off.

Every write goes through `_pump` or `_write`, and every one is decided by
the state the board last reported, applied before the write:
- a client's line is admitted twice: when it arrives, and again at the moment
  it is written. It carries the context it was admitted in (free, in a hold,
  any); if that context is gone by then (a hold began or ended, a job
  started, a lockout began), it fails with a clear error instead of running
  where it was never meant to. Waiting lines are re-checked on every change;
- lines pass the command class table (`hostd.protocol.classes`) in ALARM,
  SHUTDOWN and PANIC; job lines are not written at all then;
- job lines are not written while the job is paused (from its `!` to its
  `~`) nor while the board reports a hold; in-hold lines (`{"gc2":...}`) and
  queries go at once, past the window, through a bounded control lane;
- an exception report stops job lines until a status report says where the
  board is (an `er` may announce an alarm before its status report does);
- after `%` or 0x04 no data line is written until the board shows the flush
  happened (stat 3/4, or `er` 207): until then its answers to lines read
  before the flush still arrive and are matched; then the rest, which it
  discarded, are dropped from the books and accounted;
- a clear is sent only when none of our data lines is unanswered: the board
  runs a `{`-line ahead of waiting G-code, and a stale line must not run
  after the alarm is cleared.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from functools import partial
from typing import Any

import structlog

from hostd.config import MachineConfig
from hostd.link import Channel, LineReceived, Link, LinkError
from hostd.machine.errors import (
    Busy,
    ControllerError,
    ControllerTimeout,
    FaultActive,
    MachineError,
    NotConnected,
    Rejected,
)
from hostd.machine.events import (
    Console,
    ExceptionRaised,
    FaultDetected,
    Hub,
    LinkChanged,
    ProbeReported,
    StatusChanged,
)
from hostd.machine.linemode import InFlight, LineModeSender, SenderError
from hostd.machine.model import MachineModel
from hostd.machine.stream import JobStream, StreamEnd
from hostd.protocol.classes import CommandClass, admit, classify, classify_realtime
from hostd.protocol.commands import (
    Realtime,
    encode_clear,
    encode_get,
    encode_in_hold,
    encode_line,
    encode_realtime,
    encode_set,
    validate_line,
)
from hostd.protocol.messages import (
    Banner,
    ExceptionReport,
    Message,
    Notice,
    Response,
    StatusReport,
    Unparseable,
)
from hostd.protocol.parser import parse_line
from hostd.protocol.relaxed import parse_relaxed
from hostd.protocol.states import MachineState
from hostd.protocol.status import LOCKOUT_RAISED_BY, Status, message

log = structlog.get_logger(__name__)

# The status report list the handshake sets: the board reports these on change.
STATUS_KEYS = (
    *("stat", "line", "posx", "posy", "posz", "mpox", "mpoy", "mpoz", "vel", "feed", "unit"),
    *("coor", "dist", "frmo", "momo", "hold", "tool", "home"),
)
FLUSH_CONFIRM_TIMEOUT = 2.0
BANNER_WAIT = 1.0  # s for a banner before asking the version (a UART link prints none)
OLDEST_BUILD = 100.0  # g2core builds before 100 had other status codes
TINYG_BUILDS = 400.0  # TinyG's builds are 400 and up
RECONNECT_BACKOFF = (0.1, 0.2, 0.5, 1.0, 2.0, 5.0)

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


class Context(StrEnum):
    """What a client's line was admitted for; it is written only while that still holds."""

    FREE = "free"  # no job running, no hold: an ordinary line under the window
    HOLD = "hold"  # the board is in a hold: run inside it, in its secondary planner
    JOB = "job"  # an operation runs (a job streaming, settings, a jog): no client action fits
    OPERATION = "operation"  # a line of the running operation itself
    ANY = "any"  # queries and clears: fit every context
    OWN = "own"  # the daemon's own line


class LinkState(StrEnum):
    DOWN = "down"
    OPENING = "opening"
    HANDSHAKE = "handshake"
    READY = "ready"


Source = asyncio.Future[Response] | JobStream


@dataclass(slots=True)
class _Queued:
    """A line waiting for a slot: a client's, or the daemon's own (a clear)."""

    encoded: bytes
    cls: CommandClass
    future: asyncio.Future[Response]
    context: Context

    @property
    def own(self) -> bool:
        return self.context is Context.OWN


@dataclass(slots=True)
class _Flush:
    kind: Realtime  # QUEUE_FLUSH or JOB_KILL
    timer: asyncio.TimerHandle


class _SessionEnd(Exception):
    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class Engine:
    def __init__(
        self,
        config: MachineConfig,
        hub: Hub | None = None,
    ) -> None:
        self.config = config
        self.id = config.id
        self.hub = hub or Hub()
        self.model = MachineModel(config.id)
        self.sender = LineModeSender(config.window)
        self.link: Link | None = None
        self.link_state = LinkState.DOWN
        self.stream: JobStream | None = None
        self.console = False  # publish every line sent and received (someone listens)
        self._outbox: deque[_Queued] = deque()  # data-channel lines, under the window
        self._lane: deque[_Queued] = deque()  # queries and in-hold lines, the control lane
        self._flush: _Flush | None = None
        self._await_report = False  # an `er` came: actions and job lines wait for a report
        self._awaiting_rest = False  # the job is answered: waiting for the board to stop
        self._settings_pending = False  # refused in a lockout: sent again when it ends
        self._halted = False  # an internal fault: nothing but halts and reset is written
        self._operation = False  # the machine runs an operation: client actions are busy
        self._lines_in = 0  # lines read and understood this session (the serial fault's value)
        self._restart_deadline: float | None = None  # a reset is under way until then
        self._last_rx = 0.0
        self._banner: asyncio.Future[Banner] | None = None
        self._want = asyncio.Event()
        self._stop = asyncio.Event()
        self._ready = asyncio.Event()
        self._down = asyncio.Event()
        self._down.set()
        self._changed = asyncio.Event()  # pulsed on every answer and status report
        self._attempt_failed: asyncio.Future[str] | None = None
        self._log = log.bind(machine=config.id)

    # -- lifecycle ---------------------------------------------------------

    async def serve(self) -> None:
        """Own this machine's connection until cancelled."""
        if self.config.auto_connect:
            self._want.set()
        failures = 0
        while True:
            await self._want.wait()
            if not self.config.auto_connect:
                self._want.clear()  # this request is being served; a later one sets it again
            was_ready = await self._session()
            if self._stop.is_set():  # a disconnect was asked for
                self._stop.clear()
                continue
            failures = 0 if was_ready else failures + 1
            if self._restarting():
                # The board is rebooting: its device comes back in a moment.
                self._want.set()
                await asyncio.sleep(RECONNECT_BACKOFF[0])
            elif self._want.is_set():
                await asyncio.sleep(RECONNECT_BACKOFF[min(failures, len(RECONNECT_BACKOFF) - 1)])

    def _restarting(self) -> bool:
        deadline = self._restart_deadline
        if deadline is not None and time.monotonic() >= deadline:
            self._restart_deadline = deadline = None
        return deadline is not None

    async def connect(self) -> None:
        """Open the link and handshake; NotConnected with the reason if that fails."""
        if self.ready:
            return
        failed = self._attempt_failed
        if failed is None or failed.done():
            failed = self._attempt_failed = asyncio.get_running_loop().create_future()
        self._want.set()
        ready = asyncio.ensure_future(self._ready.wait())
        waiting: list[asyncio.Future[Any]] = [ready, failed]
        try:
            await asyncio.wait(waiting, return_when=asyncio.FIRST_COMPLETED)
        finally:
            ready.cancel()
        if not self.ready:
            reason = failed.result() if failed.done() else "not connected"
            raise NotConnected(f"{self.id}: {reason}")

    @property
    def ready(self) -> bool:
        return self.link_state is LinkState.READY

    async def disconnect(self) -> None:
        self._want.clear()
        if self.link_state is not LinkState.DOWN:
            self._stop.set()
            await self._down.wait()

    async def _session(self) -> bool:
        """One connection, opening to teardown: whether it got ready. Raises only if cancelled."""
        self.link_state = LinkState.OPENING
        self._down.clear()
        was_ready = False
        reason = "closed"
        try:
            config = self.config
            self.link = await Link.open(config.data_port, config.control_port, config.baudrate)
        except LinkError as exc:
            self._end_attempt(str(exc))
            self._teardown(str(exc))
            return False
        try:
            async with asyncio.TaskGroup() as tg:
                tg.create_task(self._read_loop(self.link))
                await self._handshake()
                was_ready = True
                self._set_ready()
                tg.create_task(self._poll_loop())
                await self._stop.wait()
                raise _SessionEnd("disconnected")
        except* _SessionEnd as group:
            reason = str(group.exceptions[0])
        except* NotConnected as group:
            reason = group.exceptions[0].message
        except* Exception as group:
            self._log.error("engine failure", exc_info=group.exceptions[0])
            reason = f"internal error: {group.exceptions[0]!r}"
        finally:
            link, self.link = self.link, None
            try:
                await link.close()  # released before anyone hears it is down
            finally:
                self._end_attempt(reason)
                self._teardown(reason)
        return was_ready

    def _set_ready(self) -> None:
        self._restart_deadline = None
        self.link_state = LinkState.READY
        self._ready.set()
        self._publish_link(True, "ready")
        self._log.info("machine ready", state=self.model.state)

    def _end_attempt(self, reason: str) -> None:
        if self._attempt_failed is not None and not self._attempt_failed.done():
            self._attempt_failed.set_result(reason)

    def _teardown(self, reason: str) -> None:
        """The link is gone: settle every line and request it carried."""
        restarted = self._restart_deadline is not None
        self.link_state = LinkState.DOWN
        self._ready.clear()
        if self._flush is not None:
            self._flush.timer.cancel()
            self._flush = None
        for entry in self.sender.clear():
            self._settle_unanswered(entry, NotConnected(f"link lost: {reason}"))
        for waiting in (self._outbox, self._lane):
            while waiting:
                self._fail(waiting.popleft().future, NotConnected(f"link lost: {reason}"))
        if self.stream is not None and not self.stream.done:
            if restarted:
                self.stream.finish(StreamEnd.FAILED, 1005, "the controller was reset")
            else:
                self.stream.finish(StreamEnd.INTERRUPTED, 1002, f"link lost: {reason}")
        self._await_report = self._awaiting_rest = False
        self._settings_pending = False
        self._lines_in = 0
        self.model.reset()
        self._log.info("link down", reason=reason)
        self._publish_link(False, reason)
        self._down.set()
        self._changed.set()

    # -- reading -----------------------------------------------------------

    async def _read_loop(self, link: Link) -> None:
        while True:
            for event in await link.read():
                if not isinstance(event, LineReceived):
                    raise _SessionEnd(event.reason)
                self._last_rx = event.at
                try:
                    self._receive(event.channel, event.line)
                except _SessionEnd:
                    raise
                except Exception as exc:  # a bug of ours: stop writing, keep reading
                    self._job_log().exception("engine invariant broken")
                    self._internal_fault(f"{type(exc).__name__}: {exc}")
            self._pump()

    def _receive(self, channel: Channel, line: bytes) -> None:
        msg = parse_line(line)
        self._log.debug("rx", channel=channel.value, line=line)
        if self.console:
            self._publish_console("rx", channel, line)
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
            self._changed.set()
            return
        elif isinstance(msg, Notice) and isinstance(msg.fields.get("prb"), dict):
            self._on_probe(msg.fields["prb"])
        else:
            self._log.debug("controller said", message=_kind(msg))
        self._lines_in += 1
        self._changed.set()

    def _on_response(self, response: Response) -> None:
        if response.count < 2:
            # No line of ours is answered with fewer than 2 (a data line of L >= 1
            # bytes gets L + 1): a report shaped as an answer (report.cpp startup
            # messages, status 15; cycle_homing.cpp's failed homing, status 240).
            self._unbooked(response)
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
            if isinstance(lost.source, JobStream):
                self._fail_job_line(lost.source, lost, "got no answer from the controller")
        if entry.own and response.status in _MALFORMED:
            # The board calls a line the daemon wrote malformed: a daemon bug.
            line = entry.line.rstrip(b"\n").decode(errors="replace")
            self._detected("syntax", line, f"{line!r} refused: {message(response.status)}")
        report = response.status_report
        if report is not None:
            self._on_status(report)
        source = entry.source
        if isinstance(source, JobStream):
            self._on_job_answer(source, entry, response)
        elif not source.done():
            source.set_result(response)

    def _unbooked(self, response: Response) -> None:
        """An `{r}` that answers no line: startup chatter is noted; anything else is an event."""
        if response.status == Status.INITIALIZING:
            self._log.info("controller initializing", msg=response.body.get("msg"))
            return
        body_msg = response.body.get("msg")
        msg = body_msg if isinstance(body_msg, str) else ""
        fields = {"st": response.status, "msg": msg}
        self._on_exception(ExceptionReport(response.status, msg, fields, response.raw))

    def _fail_job_line(self, stream: JobStream, entry: InFlight, what: str) -> None:
        """A job line went wrong on the board: the job fails, and what follows it must not run."""
        if stream.done:
            return
        stream.finish(StreamEnd.FAILED, ControllerError.code, f"line {entry.file_line}: {what}")
        self._write_realtime(Realtime.JOB_KILL)

    def _on_job_answer(self, stream: JobStream, entry: InFlight, response: Response) -> None:
        if response.ok:
            stream.acknowledged(entry.file_line)
            self._check_stream_complete()
            return
        stream.rejected += 1
        if stream.done:
            return  # already ended (an alarm, a cancel): this answer is accounted, no more
        status = response.status
        text = message(status)
        if status in (204, 205, 206):
            stream.finish(StreamEnd.FAILED, status, text)
        else:
            stream.finish(
                StreamEnd.FAILED,
                ControllerError.code,
                f"line {entry.file_line}: controller answered {status}: {text}",
            )
            # Lines already sent behind the bad one must not run: kill the job on the board.
            self._write_realtime(Realtime.JOB_KILL)

    def _on_status(self, fields: dict[str, Any]) -> None:
        before = self.model.state
        changed = self.model.apply_status(fields)
        if "stat" in fields:
            self._await_report = False
            self._confirm_flush()
            if self._awaiting_rest:
                self._check_stream_complete()
        if changed is not None:
            self._on_state(changed, before)
        if self.hub.active:
            self.hub.publish(StatusChanged(self.id, fields, self.model.snapshot()))

    def _on_exception(self, report: ExceptionReport) -> None:
        self.model.apply_exception(report)
        self._job_log().warning("controller exception", status=report.status, msg=report.message)
        if self.hub.active:
            self.hub.publish(ExceptionRaised(self.id, report.fields))
        raised = LOCKOUT_RAISED_BY.get(report.status or -1)
        if report.status == Status.JSON_OUTPUT_TOO_LONG:
            # json_parser.cpp sends this instead of the answer of the line it is on.
            self._answer_too_long()
        if raised is not None:
            lockout = MachineState[raised]
            self.model.state = lockout
            self._on_state(lockout)
        elif report.status == Status.KILL_JOB and self._flush is not None:
            self._confirm_flush(kill_seen=True)
            return
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
        if isinstance(entry.source, JobStream):
            self._fail_job_line(entry.source, entry, "its answer was too long for the controller")

    def _on_probe(self, report: dict[str, Any]) -> None:
        """A probe cycle's result (cycle_probing.cpp `_send_probe_report`): kept and told."""
        probe = self.model.apply_probe(report)
        self._job_log().info("probe", ok=probe["ok"], position=probe["position"])
        if self.hub.active:
            self.hub.publish(ProbeReported(self.id, report, probe))

    def _on_banner(self, banner: Banner) -> None:
        if self._banner is not None and not self._banner.done():
            self._banner.set_result(banner)
            return
        # SYSTEM READY mid-session: the board restarted under us.
        raise _SessionEnd("controller restarted (unexpected SYSTEM READY)")

    def _on_state(self, state: MachineState, before: MachineState | None = None) -> None:
        self._job_log().info("controller state", state=state.name)
        if before is MachineState.HOMING:
            self._ask_homed()  # a homing cycle ended, done or failed
        stream = self.stream
        if state is MachineState.RUN and stream is not None:
            stream.program_pause_sent = False
        elif (
            state in (MachineState.PROGRAM_STOP, MachineState.PROGRAM_END)
            and stream is not None
            and not stream.done
            and not stream.program_pause_sent
            and self._flush is None
            and not stream.paused  # a pause the board ignored (nothing moving) is no underflow
            and stream.peek() is not None  # lines still on the host (not only "not looked yet")
        ):
            # The board ran out of moves while the job still had lines on the host.
            where = f"after file line {stream.last_acked_line}"
            self._detected("underflow", stream.acked, f"the controller stopped {where}")
        if state.is_lockout:
            refusal = admit(CommandClass.ACTION, state)
            assert refusal is not None
            text = self.model.last_exception_message() or message(refusal)
            if self.stream is not None and not self.stream.done:
                # Drain: the job's remaining lines are dropped on the host at once.
                self.stream.finish(StreamEnd.FAILED, int(refusal), text)
        elif self._settings_pending and self.link_state is LinkState.READY:
            self._reapply_settings()
        self._recheck_waiting()

    def _context(self) -> Context:
        if self.model.state is MachineState.HOLD:
            return Context.HOLD
        return Context.JOB if self._job_running() or self._operation else Context.FREE

    def set_operation(self, running: bool) -> None:
        """The machine started or ended an operation; waiting client actions are judged again."""
        self._operation = running
        self._recheck_waiting()

    def _admissible(self, queued: _Queued, state: MachineState | None, context: Context) -> bool:
        """May this waiting line be written now? If not, its asker is told why, once."""
        verdict = admit(queued.cls, state)
        if verdict is not None:
            self._fail(queued.future, Rejected(verdict, self._locked_message()))
            return False
        if queued.context in (Context.ANY, Context.OWN) or queued.context is context:
            return True
        if queued.context is Context.OPERATION and self._operation:
            return True
        self._fail(queued.future, Busy(_context_changed(self.id, queued.context, context)))
        return False

    def _recheck_waiting(self) -> None:
        """After any change of context, fail the waiting lines it no longer admits.

        Not while a flush is under way: the board passes through a hold on its
        way to the stop that ends it, and nothing is written before then, so
        the write itself decides.
        """
        if self._flush is not None:
            return
        state, context = self.model.state, self._context()
        self._outbox = deque(q for q in self._outbox if self._admissible(q, state, context))
        self._lane = deque(q for q in self._lane if self._admissible(q, state, context))

    # -- writing -----------------------------------------------------------

    def _pump(self) -> None:
        """Fill the lane and the window: client lines first, then the job's lines, in one write.

        Every waiting line is admitted again here, against the state and
        context of this moment.
        """
        link = self.link
        if link is None or self.link_state is not LinkState.READY or self._halted:
            return
        state = self.model.state
        context = self._context()
        flushing = self._flush is not None
        unsure = flushing or self._await_report  # the board may be anywhere now
        lane = self._lane
        while lane and self.sender.control_room:
            if unsure and lane[0].context is not Context.ANY:
                break  # queries run now; an in-hold line waits to see where the board is
            queued = lane.popleft()
            if self._admissible(queued, state, context) and not self._write(
                queued.encoded, queued.future, Channel.CONTROL
            ):
                self._fail(queued.future, self._write_refused())
        if flushing:
            return  # no data line until the board shows what it discarded
        batch: list[bytes] = []
        while True:
            if self._outbox:
                head = self._outbox[0]
                if not self.sender.room(head.encoded):
                    break  # in order: a client's lines never overtake each other
                waits = (Context.FREE, Context.HOLD, Context.OPERATION)
                if self._await_report and head.context in waits:
                    break  # an exception report: actions wait for the next status report
                self._flush_batch(link, batch)
                queued = self._outbox.popleft()
                if self._admissible(queued, state, context) and not self._write(
                    queued.encoded, queued.future, Channel.DATA, own=queued.own
                ):
                    self._fail(queued.future, self._write_refused())
                continue
            stream = self.stream
            if (
                stream is None
                or stream.done
                or stream.paused
                or self._await_report
                or (state is not None and (state.is_lockout or state is MachineState.HOLD))
            ):
                break
            nxt = stream.peek()
            if nxt is None:
                self._check_stream_complete()
                break
            number, encoded = nxt
            if not self.sender.room(encoded):
                break
            try:
                self.sender.sent(InFlight(encoded, stream, number))
            except SenderError as exc:
                self._internal_fault(str(exc))
                break
            stream.take()
            batch.append(encoded)
        self._flush_batch(link, batch)

    def _flush_batch(self, link: Link, batch: list[bytes]) -> None:
        """Job lines already booked go out in one write (one syscall, not one a line)."""
        if not batch:
            return
        # A failed write means the link is already gone: the lines stay booked,
        # and teardown accounts for them with every other unanswered line.
        if link.write_lines(batch):
            if self.console:
                for line in batch:
                    self._publish_console("tx", Channel.DATA, line)
            self._log.debug("tx", channel="data", lines=len(batch))
        batch.clear()

    def _write(
        self,
        encoded: bytes,
        source: Source,
        channel: Channel,
        *,
        file_line: int | None = None,
        urgent: bool = False,
        own: bool = False,
    ) -> bool:
        link = self.link
        if link is None or self._halted:
            return False
        written = (
            link.write_line(encoded) if channel is Channel.DATA else link.write_control(encoded)
        )
        if not written:
            return False
        try:
            self.sender.sent(InFlight(encoded, source, file_line, own), urgent=urgent)
        except SenderError as exc:  # written but not booked: the books can no longer be trusted
            self._internal_fault(str(exc))
            return False
        self._log.debug("tx", channel=channel.value, line=encoded)
        if self.console:
            self._publish_console("tx", channel if link.dual else Channel.DATA, encoded)
        return True

    def _write_realtime(self, command: Realtime) -> None:
        link = self.link
        if link is None or not link.write_realtime(encode_realtime(command)):
            raise NotConnected(f"{self.id}: not connected")
        self._log.debug("tx", channel="control", line=command.value)
        if self.console:
            channel = Channel.CONTROL if link.dual else Channel.DATA
            self._publish_console("tx", channel, encode_realtime(command))
        if command in (Realtime.QUEUE_FLUSH, Realtime.JOB_KILL):
            # Whether the board flushes depends on its state *now*, which the last
            # report may not show yet: expect a flush, and let the confirmation
            # (or its absence) decide what happened to the lines in flight.
            self._begin_flush(command)

    def _query_status(self) -> asyncio.Future[Response]:
        """Ask for a full status report, ahead of anything queued."""
        future = _future()
        if not self._write(encode_get("sr"), future, Channel.CONTROL, urgent=True, own=True):
            future.set_exception(NotConnected(f"{self.id}: not connected"))
        return future

    # -- flushes -----------------------------------------------------------

    def _begin_flush(self, kind: Realtime) -> None:
        if self._flush is not None:
            self._flush.timer.cancel()
        timer = asyncio.get_running_loop().call_later(
            FLUSH_CONFIRM_TIMEOUT, self._flush_unconfirmed
        )
        self._flush = _Flush(kind, timer)
        if self.stream is not None and not self.stream.done:
            reason = "job killed" if kind is Realtime.JOB_KILL else "queue flushed"
            self.stream.finish(StreamEnd.CANCELLED, None, reason)

    def _confirm_flush(self, *, kill_seen: bool = False) -> None:
        flush = self._flush
        if flush is None:
            return
        if not kill_seen and self.model.state not in (
            MachineState.PROGRAM_STOP,
            MachineState.PROGRAM_END,
        ):
            return
        flush.timer.cancel()
        self._flush = None
        for entry in self.sender.dropped():
            self._settle_unanswered(entry, _discarded(flush.kind))
        self._pump()

    def _flush_unconfirmed(self) -> None:
        """The board did not flush (not in a hold): its lines will be answered as usual."""
        self._log.warning("flush not confirmed by the controller")
        self._flush = None
        self._pump()

    def _settle_unanswered(self, entry: InFlight, error: MachineError) -> None:
        source = entry.source
        if isinstance(source, JobStream):
            source.discarded += 1
        else:
            self._fail(source, error)

    # -- stream completion -------------------------------------------------

    def _check_stream_complete(self) -> None:
        """{r} means queued, not run: a job is done when all is answered and the board rests."""
        stream = self.stream
        if stream is None or stream.done or not stream.exhausted:
            return
        if stream.acked < stream.sent:
            return
        if not self._awaiting_rest:
            self._awaiting_rest = True
            self._query_status()  # its answer, or any later report, tells whether it rests
            return
        # At rest: PROGRAM_STOP or PROGRAM_END, or READY for a job that never moved it.
        if self.model.state is not None and self.model.state.is_resting:
            self._awaiting_rest = False
            stream.finish(StreamEnd.COMPLETED)

    # -- the handshake -----------------------------------------------------

    async def _handshake(self) -> None:
        self.link_state = LinkState.HANDSHAKE
        self._banner = asyncio.get_running_loop().create_future()
        timeout = self.config.handshake_timeout
        banner: Banner | None = None
        # After 0x18 the board boots and always prints its banner. A board on a UART
        # link prints it only at boot, not when a host opens the port: if none comes
        # soon, ask it for its version instead (g2core.md section 10).
        rebooting = self._restart_deadline is not None
        banner_wait = timeout if rebooting else min(BANNER_WAIT, timeout / 2)
        identity: float | None = None
        try:
            async with asyncio.timeout(timeout):
                try:
                    async with asyncio.timeout(banner_wait):
                        banner = await asyncio.shield(self._banner)
                    identity = banner.fb
                except TimeoutError:
                    if rebooting:
                        raise
                    answer = await self._ask(encode_get("fv", "fb"))
                    identity = _build(answer.body.get("fb"))
                _check_firmware(identity)
                for setting in self._settings():
                    response = await self._ask(encode_set(setting))
                    if response.status in _LOCKOUT_REJECTIONS:
                        # A board in ALARM refuses every SET: sent again once it is cleared.
                        self._settings_pending = True
                    elif not response.ok:
                        raise NotConnected(
                            f"controller refused {setting}: {response.status} "
                            f"({message(response.status)})"
                        )
                homed = await self._ask(encode_get("home"))
                if homed.ok:
                    self.model.apply_status({"home": homed.body.get("home")})
                await self._ask(encode_get("sr"))
        except TimeoutError:
            step = (
                "answer to its settings"
                if identity is not None
                else "SYSTEM READY banner"
                if rebooting
                else "SYSTEM READY banner, nor an answer to a version request,"
            )
            raise NotConnected(f"no {step} from the controller within {timeout:g} s") from None
        finally:
            self._banner = None

    def _settings(self) -> list[dict[str, Any]]:
        return [
            {"ej": 1},
            {"jv": 4},
            {"sv": 1},
            {"qv": 0},
            {"si": round(self.config.status_interval * 1000)},
            {"sr": dict.fromkeys((*STATUS_KEYS, *self.config.signals.keys()), True)},
        ]

    def _ask_homed(self) -> None:
        """`{home:n}`: whether the board is homed comes from the board, never a guess."""
        future = _future()
        future.add_done_callback(self._homed_answered)
        self._write(encode_get("home"), future, Channel.CONTROL, urgent=True, own=True)

    def _homed_answered(self, future: asyncio.Future[Response]) -> None:
        if not future.cancelled() and future.exception() is None and future.result().ok:
            self.model.apply_status({"home": future.result().body.get("home")})

    def _reapply_settings(self) -> None:
        self._settings_pending = False
        for setting in self._settings():
            future = _future()
            future.add_done_callback(partial(self._setting_answered, setting))
            if not self._write(encode_set(setting), future, Channel.CONTROL, urgent=True, own=True):
                return

    def _setting_answered(self, setting: dict[str, Any], future: asyncio.Future[Response]) -> None:
        if future.cancelled() or future.exception() is not None:
            return
        if not future.result().ok:
            self._log.error("controller refused a setting", setting=setting)

    async def _ask(self, encoded: bytes) -> Response:
        """A daemon line outside any job, answered before the next is sent."""
        future = _future()
        if not self._write(encoded, future, Channel.CONTROL, urgent=True, own=True):
            raise NotConnected(f"{self.id}: link lost")
        return await future

    # -- the poller --------------------------------------------------------

    async def _poll_loop(self) -> None:
        """A silent board is asked for a report; one that stays silent is gone."""
        heartbeat = self.config.heartbeat
        while True:
            quiet_until = self._last_rx + heartbeat
            now = time.monotonic()
            if now < quiet_until:
                await asyncio.sleep(quiet_until - now)
                continue
            probe = self._query_status()
            try:
                async with asyncio.timeout(heartbeat):
                    await asyncio.shield(probe)
            except TimeoutError:
                raise _SessionEnd(
                    f"controller silent for {2 * heartbeat:g} s (no answer to a status request)"
                ) from None

    # -- requests ----------------------------------------------------------

    def _require_ready(self) -> None:
        if self.link_state is not LinkState.READY:
            raise NotConnected(f"{self.id} is not connected")

    async def send(self, line: str, timeout: float = 10.0, *, operation: bool = False) -> Response:
        """One line from a client, answered by the board (ControllerError for a non-zero status).

        `operation`: the line is the running operation's own (a settings batch, a
        jog's G90), not a client's; it fits while that operation runs.
        """
        self._require_ready()
        if self._halted:
            raise self._write_refused()
        validate_line(line)
        cls = classify(line)
        text = line.strip()
        verdict = admit(cls, self.model.state)
        if verdict is not None:
            raise Rejected(verdict, self._locked_message())
        future = _future()
        if cls is CommandClass.QUERY:
            # As a JSON GET it is run on arrival: it never waits behind queued G-code.
            self._lane.append(_Queued(_as_json_query(text), cls, future, Context.ANY))
        elif cls is CommandClass.CLEAR:
            self._outbox.append(_Queued(encode_line(text), cls, future, Context.ANY))
        elif operation and self._operation and self._context() is Context.JOB:
            self._outbox.append(_Queued(encode_line(text), cls, future, Context.OPERATION))
        else:
            self._admit_action(text, cls, future)
        self._pump()
        return await self._answer(future, timeout)

    def _admit_action(self, text: str, cls: CommandClass, future: asyncio.Future[Response]) -> None:
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
            self._outbox.append(_Queued(encode_line(text), cls, future, context))
            return
        if text.startswith("$"):
            # A text line is data: the board would keep it until the hold ends.
            raise Busy(f"{self.id} is in a hold: send settings as JSON ({{key:value}})")
        encoded = encode_in_hold(text) if _is_gcode(text) else encode_line(text)
        self._lane.append(_Queued(encoded, cls, future, context))

    async def _answer(self, future: asyncio.Future[Response], timeout: float) -> Response:
        try:
            async with asyncio.timeout(timeout):
                response = await asyncio.shield(future)
        except TimeoutError:
            self._outbox = deque(q for q in self._outbox if q.future is not future)
            self._lane = deque(q for q in self._lane if q.future is not future)
            future.cancel()
            raise ControllerTimeout(f"no answer from {self.id} within {timeout:g} s") from None
        if not response.ok:
            raise ControllerError(response.status, message(response.status))
        return response

    def realtime(self, command: Realtime) -> None:
        """Write a realtime byte now (it never waits), if the state admits it."""
        if self.link is None or self.link_state is LinkState.DOWN:
            raise NotConnected(f"{self.id} is not connected")
        state = self.model.state
        cls = classify_realtime(command)
        verdict = admit(cls, state)
        if verdict is not None:
            raise Rejected(verdict, self._locked_message())
        if self._halted and cls not in (CommandClass.HALT, CommandClass.RESET):
            raise self._write_refused()
        self._write_realtime(command)

    async def clear(self, timeout: float = 5.0) -> None:
        """Leave ALARM or SHUTDOWN with `{clear:n}`; PANIC is refused; otherwise a no-op."""
        self._require_ready()
        state = self.model.state
        if state is MachineState.PANIC:
            raise Rejected(Status.COMMAND_REJECTED_BY_PANIC, "PANIC is left only by a reset")
        if state not in (MachineState.ALARM, MachineState.SHUTDOWN):
            return
        try:
            async with asyncio.timeout(timeout):
                await self.wait_for(self._no_data_in_flight)
        except TimeoutError:
            raise ControllerTimeout(
                f"{self.id}: lines still unanswered in the controller; not clearing"
            ) from None
        future = _future()
        self._outbox.append(_Queued(encode_clear(), CommandClass.CLEAR, future, Context.OWN))
        self._pump()
        await self._answer(future, timeout)
        try:
            async with asyncio.timeout(timeout):
                await self.wait_for(lambda: not _locked(self.model.state))
        except TimeoutError:
            raise ControllerTimeout(f"{self.id} did not leave {state.name}") from None

    async def reset(self, timeout: float = 10.0) -> None:
        """0x18: the board reboots; reconnect, handshake again, and return once ready."""
        if self.link is None:
            raise NotConnected(f"{self.id} is not connected")
        self._restart_deadline = time.monotonic() + timeout
        self._ready.clear()
        self._write_realtime(Realtime.RESET)
        self._halted = False  # the controller restarts; so do the daemon's books
        try:
            async with asyncio.timeout(timeout):
                await self._down.wait()
                await self._ready.wait()
        except TimeoutError:
            raise ControllerTimeout(f"{self.id} did not come back after reset") from None

    def admit_action(self) -> None:
        """Rejected (204/205/206) if an action may not reach the board now."""
        verdict = admit(CommandClass.ACTION, self.model.state)
        if verdict is not None:
            raise Rejected(verdict, self._locked_message())

    def start_stream(self, stream: JobStream) -> None:
        self._require_ready()
        if self._job_running():
            raise Busy(f"{self.id} is running a job")
        self.admit_action()
        self.stream = stream
        self._awaiting_rest = False
        self._recheck_waiting()  # a client line still waiting was not admitted into a job
        self._pump()

    def pause_stream(self) -> None:
        """The job's pause: `!`, and none of its lines is written until `resume_stream`."""
        stream = self._live_stream()
        self.realtime(Realtime.FEEDHOLD)
        stream.paused = True

    def resume_stream(self) -> None:
        """The job's resume: `~`, and its lines flow again."""
        stream = self._live_stream()
        if not stream.paused:
            raise Busy(f"{self.id}: the job is not paused")
        self.realtime(Realtime.CYCLE_START)
        stream.paused = False
        self._pump()

    def _live_stream(self) -> JobStream:
        stream = self.stream
        if stream is None or stream.done:
            raise Busy(f"{self.id} has no job streaming")
        return stream

    def out_of_hold(self) -> bool:
        """No hold on the board and no flush under way: a free line is written as it is."""
        return self._flush is None and self.model.state is not MachineState.HOLD

    def _job_running(self) -> bool:
        return self.stream is not None and not self.stream.done

    def _no_data_in_flight(self) -> bool:
        return not any(not e.control for e in self.sender.pending())

    def quiet(self) -> bool:
        """Nothing of the host's queued or unanswered, but for queries."""
        return not self._outbox and self._no_data_in_flight() and not self._job_running()

    async def wait_for(self, predicate: Callable[[], bool]) -> None:
        """Until the predicate holds, re-checked after every answer and report.

        NotConnected if the link goes down first.
        """
        while not predicate():
            if self.link_state is LinkState.DOWN:
                raise NotConnected(f"{self.id}: link lost")
            self._changed.clear()
            await self._changed.wait()

    # -- helpers -------------------------------------------------------------

    def _job_log(self) -> Any:
        """The machine's logger, with `job=` while a job runs."""
        stream = self.stream
        if stream is None or stream.done or stream.job_id is None:
            return self._log
        return self._log.bind(job=stream.job_id)

    def _detected(self, fault: str, value: Any, text: str) -> None:
        self.hub.publish(FaultDetected(self.id, fault, value, text))

    def _internal_fault(self, text: str) -> None:
        """The daemon broke one of its own invariants here: write nothing more until reset."""
        self._halted = True
        if self.stream is not None and not self.stream.done:
            self.stream.finish(StreamEnd.FAILED, FaultActive.code, f"internal fault: {text}")
        self._detected("internal", None, text)

    def _write_refused(self) -> MachineError:
        if self._halted:
            return FaultActive(
                f"{self.id}: internal fault, nothing is written until machine.reset", ["internal"]
            )
        return NotConnected(f"{self.id}: link lost")

    def stop_stream(self, code: int, text: str) -> None:
        """Fail the running job and stop the board: feedhold, then flush (a fault's effect)."""
        if self.stream is None or self.stream.done:
            return
        self.stream.finish(StreamEnd.FAILED, code, text)
        if self.link is not None:
            self._write_realtime(Realtime.FEEDHOLD)
            self._write_realtime(Realtime.QUEUE_FLUSH)

    def _locked_message(self) -> str:
        state = self.model.state
        name = state.name if state is not None else "an unknown state"
        detail = self.model.last_exception_message()
        return f"{self.id} is in {name}" + (f": {detail}" if detail else "")

    def _fail(self, future: asyncio.Future[Response], error: MachineError) -> None:
        if not future.done():
            future.set_exception(error)

    def _publish_console(self, direction: str, channel: Channel, line: bytes) -> None:
        text = line.rstrip(b"\n").decode("utf-8", "backslashreplace")
        self.hub.publish(Console(self.id, direction, str(channel), text))

    def _publish_link(self, up: bool, reason: str) -> None:
        if self.hub.active:
            self.hub.publish(LinkChanged(self.id, up, reason))


def _future() -> asyncio.Future[Response]:
    """A future for an answer. Its outcome counts as seen even if its asker is gone."""
    future: asyncio.Future[Response] = asyncio.get_running_loop().create_future()
    future.add_done_callback(_seen)
    return future


def _seen(future: asyncio.Future[Response]) -> None:
    if not future.cancelled():
        future.exception()


def _discarded(kind: Realtime) -> MachineError:
    status = Status.KILL_JOB if kind is Realtime.JOB_KILL else Status.NOOP
    what = "job kill" if kind is Realtime.JOB_KILL else "queue flush"
    return ControllerError(int(status), f"discarded by the controller's {what} before it ran")


def _locked(state: MachineState | None) -> bool:
    return state is not None and state.is_lockout


def _build(value: object) -> float | None:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


def _check_firmware(fb: float | None) -> None:
    """g2core from build 100 only: TinyG's codes differ, and before 100 so did g2core's."""
    if fb is None:
        raise NotConnected("the controller did not say its firmware build (fb)")
    if fb >= TINYG_BUILDS:
        raise NotConnected(
            f"TinyG firmware (build {fb:g}) is not supported: its status codes differ from g2core's"
        )
    if fb < OLDEST_BUILD:
        raise NotConnected(
            f"g2core build {fb:g} is older than {OLDEST_BUILD:.2f}, whose status codes hostd "
            "relies on (204 meant something else before): update the firmware"
        )


def _context_changed(machine: str, admitted: Context, now: Context) -> str:
    what = {
        Context.HOLD: "a hold began",
        Context.JOB: "an operation started",
        Context.FREE: "the hold ended",
    }[now]
    if admitted is Context.HOLD and now is not Context.HOLD:
        what = "the hold ended"
    return f"{machine}: {what} before the line was written; it was not sent"


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


def _kind(msg: Message) -> str:
    return type(msg).__name__
