"""One machine's engine: the I/O shell around its dialect's session.

The engine holds no protocol rule; the session of the machine's dialect
holds them all. The engine opens the link, feeds the session every line the
board prints and every request a client makes, writes what the session says
to write, runs the one timer the session asks for, and delivers the
session's events: answers to the futures that wait for them, a job's end
to its JobStream, and everything else up to its Machine, through one typed
callback (`on_event`, an `EngineEvent`). The Machine decides what becomes
public (hostd/machine/machine.py); the engine never publishes.

Events are delivered only after the step that raised them is over (the
lines of one read; a request taken; a timer). A command the Machine gives
while an event is being handed to it (stopping a job for a fault, marking
an operation) is not run there: it is queued, and
the delivery loop runs it once the whole batch is handed out, then writes
its consequences in the same step. Nothing re-enters the session from
inside its own receive step, nor from inside the delivery of its events.

A job's lines reach the session the same way: after every step the engine
feeds the running job's session position from its file (`JobStream.fill`),
at most LOOK_AHEAD lines ahead, and pumps again at once when the session
had room and nothing to send.

`serve()` owns the connection for the life of the daemon: it opens the link
when asked (or at once with `auto_connect`), runs one connection until the
link is lost, the session closes it, or a disconnect is asked, tears it down
as one, and reconnects with back-off.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable, Iterator
from enum import StrEnum
from typing import Any

import structlog

from hostd.link import Channel, Link, LinkError
from hostd.machine.config import MachineConfig
from hostd.machine.events import (
    Console,
    EngineEvent,
    ExceptionRaised,
    FaultDetected,
    LinkChanged,
    ProbeReported,
    StatusChanged,
)
from hostd.machine.stream import JobStream
from hostd.protocol.commands import Realtime
from hostd.protocol.errors import (
    ControllerError,
    ControllerTimeout,
    NotConnected,
)
from hostd.protocol.messages import Response
from hostd.protocol.model import MachineModel
from hostd.protocol.session import SessionBase
from hostd.protocol.stream import Stream
from hostd.protocol.vocabulary import (
    Closing,
    Detected,
    Event,
    Excepted,
    Lane,
    Probed,
    Ready,
    Reported,
    Settled,
    StreamEnded,
)

log = structlog.get_logger(__name__)

RECONNECT_BACKOFF = (0.1, 0.2, 0.5, 1.0, 2.0, 5.0)


class LinkState(StrEnum):
    DOWN = "down"
    OPENING = "opening"
    HANDSHAKE = "handshake"
    READY = "ready"


class Engine:
    def __init__(
        self, config: MachineConfig, on_event: Callable[[EngineEvent], None] | None = None
    ) -> None:
        self.config = config
        self.id = config.id
        self._on_up: Callable[[EngineEvent], None] = on_event or _ignore  # the way up: one
        self.session = session_for(config)
        self._job: JobStream | None = None  # the job streaming: its file feeds the session
        self.link: Link | None = None
        self.link_state = LinkState.DOWN
        self.console = False  # publish every line sent and received (someone listens)
        # Publish every line but a running job's own and their plain answers (someone
        # listens without them: `job_lines: false`). Without `console` those lines are not
        # even decoded: at a laser's 1,000-2,000 lines/s they were two events a line.
        self.console_but_job = False
        # Publish status polls and reports among those lines (someone listens with them:
        # `status_traffic`, the default). Off, they are not even decoded.
        self.console_status = True
        # The job's `sent` count at the last write: the lines it wrote since are the job's.
        self._sent_stream: Stream | None = None
        self._sent_seen = 0
        self._restart_deadline: float | None = None  # a reset is under way until then
        self._delivering = False  # the delivery loop runs: a nested call leaves it the work
        self._handing_out = False  # events go up now: a command given meanwhile is queued
        self._deferred: list[Callable[[], None]] = []  # run once the events are handed out
        self._write_failed = False
        self._timer: asyncio.TimerHandle | None = None
        self._timer_at: float | None = None
        self._closed: asyncio.Future[str] | None = None  # this connection's end, with why
        self._want = asyncio.Event()
        self._stop = asyncio.Event()
        self._ready = asyncio.Event()
        self._down = asyncio.Event()
        self._down.set()
        self._changed = asyncio.Event()  # pulsed after every step that may change a state
        self._attempt_failed: asyncio.Future[str] | None = None
        self._hold_reopen = False  # the session gave up a board that may move: wait to be asked
        self._log = log.bind(machine=config.id)
        # Whether a line read or written is logged: asked once, not at every line.
        self._traffic_logged = _debug_enabled(self._log)

    @property
    def model(self) -> MachineModel:
        return self.session.model

    # -- lifecycle ---------------------------------------------------------

    async def serve(self) -> None:
        """Own this machine's connection until cancelled."""
        if self.config.auto_connect:
            self._want.set()
        failures = 0
        while True:
            await self._want.wait()
            self._hold_reopen = False
            if not self.config.auto_connect:
                self._want.clear()  # this request is being served; a later one sets it again
            was_ready = await self._connection()
            if self._stop.is_set():  # a disconnect was asked for
                self._stop.clear()
                continue
            failures = 0 if was_ready else failures + 1
            if self._hold_reopen:
                continue  # until connect() asks: `_want` is clear
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
            await asyncio.wait({ready})  # it ends here, not after its asker (never re-raises)
        if not self.ready:
            reason = failed.result() if failed.done() else "not connected"
            raise NotConnected(f"{self.id}: {reason}")

    @property
    def ready(self) -> bool:
        """Clients may use the board (not while a grbl board re-syncs after its reset)."""
        return self.link_state is LinkState.READY and self.session.ready

    async def disconnect(self) -> None:
        self._want.clear()
        if self.link_state is not LinkState.DOWN:
            self._stop.set()
            self._end("disconnected")
            await self._down.wait()

    async def _connection(self) -> bool:
        """One connection, opening to teardown: whether it got ready. Raises only if cancelled."""
        self.link_state = LinkState.OPENING
        self._down.clear()
        config = self.config
        try:
            self.link = await Link.open(
                config.data_port, config.control_port, config.baudrate, receiver=self
            )
        except LinkError as exc:
            self._end_attempt(str(exc))
            self._teardown(str(exc))
            return False
        closed = self._closed = asyncio.get_running_loop().create_future()
        if self._stop.is_set():
            closed.set_result("disconnected")
        reason = "closed"
        try:
            self.link_state = LinkState.HANDSHAKE
            self.session.open(rebooting=self._restart_deadline is not None)
            self._deliver()
            reason = await closed
        finally:
            was_ready = self.link_state is LinkState.READY
            link, self.link = self.link, None
            try:
                await link.close()  # released before anyone hears it is down
            finally:
                self._end_attempt(reason)
                self._teardown(reason)
        return was_ready

    def _end(self, reason: str) -> None:
        """This connection is over: its task tears it down."""
        if self._closed is not None and not self._closed.done():
            self._closed.set_result(reason)

    def _on_ready(self) -> None:
        self._restart_deadline = None
        self.link_state = LinkState.READY
        self._ready.set()
        self._publish_link(True, "ready")
        self._log.info("machine ready", state=self.model.state)

    def _end_attempt(self, reason: str) -> None:
        if self._attempt_failed is not None and not self._attempt_failed.done():
            self._attempt_failed.set_result(reason)

    def _teardown(self, reason: str) -> None:
        """The link is gone: the session settles every line and request it carried."""
        self.link_state = LinkState.DOWN
        self._ready.clear()
        self._closed = None
        self.session.close(reason, restarted=self._restart_deadline is not None)
        self._deliver()
        if self._timer is not None:
            self._timer.cancel()
            self._timer = self._timer_at = None
        self._log.info("link down", reason=reason)
        self._publish_link(False, reason)
        self._down.set()
        self._changed.set()

    # -- reading: the link's callbacks -------------------------------------

    def link_lines(self, channel: Channel, lines: list[bytes]) -> None:
        """Lines as the link read them, in its read callback: no inbox, no task switch.

        A read is one step: every line it holds goes to the session, then what
        they freed is written in one write. (Until issue 30 a read that could
        answer every line the board held wrote the first freed line at once,
        so that the board worked while the daemon read the rest: on a shared,
        unpinned machine that second write woke the board for one line and
        broke the answers into one-line reads, which cost twice the CPU a line;
        docs/performance.md.)
        """
        if self.link is None:
            return  # a read that raced the teardown
        if self._traffic_logged:
            for line in lines:
                self._log.debug("rx", channel=channel.value, line=line)
        if self.console:
            self._receive_published(channel, lines)  # line by line: each is published
        else:
            self._receive(lines, channel if self.console_but_job else None)
        try:
            self._deliver()
        except Exception as exc:  # never into the transport's callback: end it
            self._log.exception("engine failure")
            self._end(f"internal error: {exc!r}")

    def _receive(self, lines: list[bytes], published: Channel | None = None) -> None:
        """The read's lines to the session: each run of plain job answers in one pass
        (`receive_plain`), anything else in full at its place.

        With `published` (someone listens to the console without the job's lines)
        each line taken in full is published as it is, unless it answered a job
        line; the plain answers taken in one pass are the job's, and never are.
        """
        session = self.session
        receive, plain = session.receive, session.receive_plain
        count = len(lines)
        index = 0
        while index < count:
            at = index
            try:
                at = plain(lines, index)
                if at < count:
                    if published is None:
                        receive(lines[at])
                    else:
                        self._receive_one(published, lines[at])
            except Exception as exc:  # a bug of ours: stop writing, keep reading
                self._log.exception("engine invariant broken")
                session.halt(f"{type(exc).__name__}: {exc}")
            index = at + 1

    def _receive_published(self, channel: Channel, lines: list[bytes]) -> None:
        """`receive` for each line, each published as a console event after it is taken."""
        for line in lines:
            self._receive_one(channel, line)

    def _receive_one(self, channel: Channel, line: bytes) -> None:
        """`receive` for one line, then its console event: after, so that the job's
        count says whether the line was the plain answer (status 0) to one of the
        job's lines (the stream's `acked` moved by one). The event still goes out
        before any the line caused (those are handed out once the whole read is
        taken)."""
        session = self.session
        stream = session.stream
        acked = stream.acked if stream is not None else 0
        try:
            session.receive(line)
        except Exception as exc:  # a bug of ours: stop writing, keep reading
            self._log.exception("engine invariant broken")
            session.halt(f"{type(exc).__name__}: {exc}")
        job = stream is not None and stream.acked == acked + 1
        if job and not self.console:
            return
        self._publish_console("rx", channel, line, job)

    def link_lost(self, reason: str) -> None:
        self._end(reason)

    # -- the delivery loop -------------------------------------------------

    def _deliver(self) -> None:
        """Write what the session says, then hand out its events, until it has nothing more.

        A command the Machine gives while it hears the events (a fault stopping
        a job) waits until they are all handed out; this loop then runs it and
        writes what it adds. After each pass the running job is fed from its file.
        """
        if self._delivering:
            return
        self._delivering = True
        session = self.session
        try:
            while True:
                writes = session.data_to_send()
                events = session.events()
                if writes:
                    self._write(writes)
                if events:
                    self._hand_out(events)
                deferred = self._deferred
                if deferred:  # the Machine's commands, given while it heard the events
                    self._deferred = []
                    for command in deferred:
                        command()
                job = self._job
                # The board is at work on what was written: feed the lines after it. If the
                # session had room and no line, or the file ended, it is pumped again now.
                if job is not None and job.fill():
                    continue
                if not events and not deferred:
                    break  # writing changes nothing in the session: it has no more to say
            job = self._job
            if job is not None:
                job.stepped()
        finally:
            self._delivering = False
            self._handing_out = False
        self._changed.set()
        self._arm_timer()

    @contextlib.contextmanager
    def one_step(self) -> Iterator[None]:
        """Several calls as one step: what they write goes out together, at the end.

        The machine resumes a job and moves its supervisor in one step, so
        that no job line is written, nor published, while it still says paused.
        """
        if self._delivering:
            yield
            return
        self._delivering = True
        try:
            yield
        finally:
            self._delivering = False
            self._deliver()

    def _write(self, writes: list[tuple[Lane, bytes]]) -> None:
        """Consecutive lines of one lane go out in one write (one syscall, not one a line)."""
        link = self.link
        if link is None:
            return
        ok = True
        job = (self.console or self.console_but_job) and self._all_data_is_job(writes)
        batch: list[bytes] = []
        batch_lane: Lane | None = None
        for lane, data in writes:
            if lane is batch_lane:
                batch.append(data)
                continue
            if batch_lane is not None:
                ok = self._write_batch(link, batch_lane, batch, job) and ok
            if lane is Lane.REALTIME:
                ok = link.write_realtime(data) and ok
                self._tx(link, lane, [data])
                batch, batch_lane = [], None
            else:
                batch, batch_lane = [data], lane
        if batch_lane is not None:
            ok = self._write_batch(link, batch_lane, batch, job) and ok
        # A failed write means the link is already gone: the lines stay booked,
        # and teardown accounts for them with every other unanswered line.
        self._write_failed = not ok

    def _all_data_is_job(self, writes: list[tuple[Lane, bytes]]) -> bool:
        """Whether every data-lane line of these writes is a line of the running job.

        The job's `sent` count moves when the session books a job line for writing,
        so the lines it moved by since the last write are the job's. Only when they
        are all the data lines here (no query admitted among them) are they called
        the job's; otherwise all are shown: leaving out too little is harmless.
        """
        stream = self.session.stream
        if stream is None:
            self._sent_stream = None
            return False
        sent = stream.sent
        before = self._sent_seen if self._sent_stream is stream else 0
        self._sent_stream, self._sent_seen = stream, sent
        if sent == before:
            return False
        return sent - before == sum(1 for lane, _ in writes if lane is Lane.DATA)

    def _write_batch(self, link: Link, lane: Lane, lines: list[bytes], job: bool) -> bool:
        ok = link.write_lines(lines, control=lane is Lane.CONTROL)
        if self._traffic_logged or self.console or self.console_but_job:  # `_tx`'s own test
            self._tx(link, lane, lines, job and lane is Lane.DATA)
        return ok

    def _tx(self, link: Link, lane: Lane, lines: list[bytes], job: bool = False) -> None:
        if not (self._traffic_logged or self.console or self.console_but_job):
            return
        if self._traffic_logged:  # else only the console listens: no debug record is kept
            if lane is Lane.DATA and len(lines) > 1:
                self._log.debug("tx", lane=lane.value, lines=len(lines))  # a job's window
            else:
                for line in lines:
                    self._log.debug("tx", lane=lane.value, line=line)
        if self.console or (self.console_but_job and not job):
            channel = Channel.CONTROL if lane is not Lane.DATA and link.dual else Channel.DATA
            for line in lines:
                self._publish_console("tx", channel, line, job)

    def _hand_out(self, events: list[Event]) -> None:
        self._handing_out = True
        for event in events:
            self._on_event(event)
        self._handing_out = False

    def _up(self, event: EngineEvent) -> None:
        """To the Machine; its failure is logged, never let into the delivery loop."""
        try:
            self._on_up(event)
        except Exception:
            self._log.exception("the machine failed on an engine event", kind=type(event).__name__)

    def _command(self, command: Callable[[], None]) -> None:
        """Run a command of the Machine's now, or, while events are being handed out,
        once they all are (the delivery loop runs it and writes what it says)."""
        if self._handing_out:
            self._deferred.append(command)
            return
        command()
        self._deliver()

    def _on_event(self, event: Event) -> None:
        if isinstance(event, Settled):
            future = event.token
            if not future.done():
                if isinstance(event.outcome, Response):
                    future.set_result(event.outcome)
                else:
                    future.set_exception(event.outcome)
        elif isinstance(event, Reported):
            self._up(StatusChanged(self.id, event.fields, event.snapshot))
        elif isinstance(event, StreamEnded):
            job = self._job
            if job is not None and job.position.done:
                self._job = None
                job.ended(event.result)
        elif isinstance(event, Excepted):
            self._up(ExceptionRaised(self.id, event.fields))
        elif isinstance(event, Detected):
            self._up(FaultDetected(self.id, event.fault, event.value, event.message))
        elif isinstance(event, Probed):
            self._up(ProbeReported(self.id, event.report, event.probe))
        elif isinstance(event, Ready):
            self._on_ready()
        elif isinstance(event, Closing):
            if not event.reopen:
                # The board may be moving: reopening its port could reset it (an Arduino's
                # DTR). Only a connect asked for (machine.connect) opens it again.
                self._log.warning("link given up; not reopened on its own", reason=event.reason)
                self._want.clear()
                self._hold_reopen = True
            self._end(event.reason)

    def _arm_timer(self) -> None:
        """One timer, at the session's next deadline; an early wake-up is harmless."""
        deadline = self.session.next_deadline()
        if deadline is None or (self._timer_at is not None and self._timer_at <= deadline):
            return
        if self._timer is not None:
            self._timer.cancel()
        delay = max(0.0, deadline - time.monotonic())
        self._timer = asyncio.get_running_loop().call_later(delay, self._on_timer)
        self._timer_at = deadline

    def _on_timer(self) -> None:
        self._timer = self._timer_at = None
        if self.link_state is LinkState.DOWN:
            return
        try:
            self.session.tick()
        except Exception as exc:
            self._log.exception("engine invariant broken")
            self.session.halt(f"{type(exc).__name__}: {exc}")
        self._deliver()

    # -- requests ----------------------------------------------------------

    def _future(self) -> asyncio.Future[Response]:
        """A future for an answer. Its outcome counts as seen even if its asker is gone."""
        future: asyncio.Future[Response] = asyncio.get_running_loop().create_future()
        future.add_done_callback(_seen)
        return future

    async def send(self, line: str, timeout: float = 10.0, *, operation: bool = False) -> Response:
        """One line from a client, answered by the board (ControllerError for a non-zero status).

        `operation`: the line is the running operation's own (a settings batch, a
        jog's G90), not a client's; it fits while that operation runs.
        """
        future = self._future()
        self.session.send(line, future, operation=operation)
        self._deliver()
        return await self._answer(future, timeout)

    async def _answer(self, future: asyncio.Future[Response], timeout: float) -> Response:
        """The board's answer, or ControllerTimeout; a line not yet written then never is.

        One timer a request, not a timeout scope and a shield: a query flood
        makes thousands of these a second, and a feedhold waits behind them.
        """
        timer = asyncio.get_running_loop().call_later(timeout, self._expire, future, timeout)
        try:
            response = await future
        except asyncio.CancelledError:
            self.session.cancel(future)  # the asker is gone: its line, if still waiting, too
            raise
        finally:
            timer.cancel()
        if not response.ok:
            raise ControllerError(response.status, self.session.status_text(response.status))
        return response

    async def alarm(self) -> Response:
        """Raise an alarm on the board, in its dialect's words (InvalidCommand if it has none)."""
        return await self.send(self.session.alarm_line())

    async def shutdown(self) -> Response:
        """Raise a shutdown on the board, in its dialect's words (InvalidCommand if it has none)."""
        return await self.send(self.session.shutdown_line())

    def _expire(self, future: asyncio.Future[Response], timeout: float) -> None:
        if not future.done():
            self.session.cancel(future)
            future.set_exception(
                ControllerTimeout(f"no answer from {self.id} within {timeout:g} s")
            )

    def realtime(self, command: Realtime) -> None:
        """Write a realtime byte now (it never waits), if the state admits it."""
        if self.link is None or self.link_state is LinkState.DOWN:
            raise NotConnected(f"{self.id} is not connected")
        self.session.realtime(command)
        self._deliver()
        if self._write_failed:
            raise NotConnected(f"{self.id}: not connected")

    def override(
        self, feed: int | None = None, rapid: int | None = None, spindle: int | None = None
    ) -> None:
        """Feed, rapid and spindle overrides, in percent, written now (realtime)."""
        self.session.override(feed, rapid, spindle)
        self._deliver()

    def safety_door(self) -> None:
        """The safety door opened, as the host says (grbl's 0x84)."""
        self.session.safety_door()
        self._deliver()

    def query_status(self) -> None:
        """Ask the board for a full status report now."""
        self.session.query_status()
        self._deliver()

    async def clear(self, timeout: float = 5.0) -> None:
        """Leave ALARM or SHUTDOWN with `{clear:n}`; PANIC is refused; otherwise a no-op.

        The session writes the clear only once none of our data lines is unanswered.
        """
        future = self._future()
        if not self.session.clear(future):
            return
        state = self.model.state
        self._deliver()
        await self._answer(future, timeout)
        try:
            async with asyncio.timeout(timeout):
                await self.wait_for(lambda: not self.session.locked())
        except TimeoutError:
            name = state.name if state is not None else "its lockout"
            raise ControllerTimeout(f"{self.id} did not leave {name}") from None

    async def reset(self, timeout: float = 10.0) -> None:
        """0x18: the board restarts; return once it is ready again.

        A g2core board reboots (its USB device goes away: the engine reconnects);
        a grbl board resets in place and its session re-syncs on the same link.
        """
        if self.link is None:
            raise NotConnected(f"{self.id} is not connected")
        self._restart_deadline = time.monotonic() + timeout
        self._ready.clear()
        self.session.reset()
        self._deliver()
        try:
            async with asyncio.timeout(timeout):
                await self._ready.wait()
        except TimeoutError:
            raise ControllerTimeout(f"{self.id} did not come back after reset") from None

    def admit_action(self) -> None:
        """Rejected (204/205/206) if an action may not reach the board now."""
        self.session.admit_action()

    def set_operation(self, running: bool) -> None:
        """The machine started or ended an operation; waiting client actions are judged again.

        Given while the Machine hears an event, it runs once the events are handed out.
        """
        self._command(lambda: self.session.set_operation(running))

    def start_stream(self, stream: JobStream) -> None:
        """Stream a job: the session takes its position, and the file feeds it from now on."""
        self.session.start_stream(stream.start(self.session.encode_job_line))
        self._job = stream
        stream.fill()
        self._deliver()

    def pause_stream(self) -> None:
        """The job's pause: `!`, and none of its lines is written until `resume_stream`."""
        self.session.pause_stream()
        self._deliver()

    def resume_stream(self) -> None:
        """The job's resume: `~`, and its lines flow again."""
        self.session.resume_stream()
        self._deliver()

    def release_stream(self) -> None:
        """Pass the job's hold point (a tool change answered): its lines flow again."""
        self.session.release_stream()
        self._deliver()

    def stop_stream(self, code: int, text: str) -> None:
        """Fail the running job and stop the board: feedhold, then flush (a fault's effect).

        Given while the Machine hears an event, it runs once the events are handed out.
        """
        self._command(lambda: self.session.stop_stream(code, text))

    # -- views -------------------------------------------------------------

    def out_of_hold(self) -> bool:
        """No hold on the board and no flush under way: a free line is written as it is."""
        return self.session.out_of_hold()

    def quiet(self) -> bool:
        """Nothing of the host's queued or unanswered, but for queries; no stop under way."""
        return self.session.quiet()

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

    def _publish_console(
        self, direction: str, channel: Channel, line: bytes, job: bool = False
    ) -> None:
        status = not job and self.session.status_traffic(line, direction == "tx")
        if status and not self.console_status:
            return
        text = line.rstrip(b"\n").decode("utf-8", "backslashreplace")
        self._up(Console(self.id, direction, str(channel), text, job, status))

    def _publish_link(self, up: bool, reason: str) -> None:
        self._up(LinkChanged(self.id, up, reason))


def _debug_enabled(logger: Any) -> bool:
    """Whether a structlog logger passes debug records (True if it cannot say)."""
    is_enabled_for = getattr(logger, "is_enabled_for", None)
    return True if is_enabled_for is None else bool(is_enabled_for(logging.DEBUG))


def session_for(config: MachineConfig) -> SessionBase:
    """The session of the machine's dialect (its registry entry's): every protocol rule is in it."""
    return config.spec.session(config)


def _ignore(_: EngineEvent) -> None:
    """An engine nobody follows (a test's): its events go nowhere."""


def _seen(future: asyncio.Future[Response]) -> None:
    if not future.cancelled():
        future.exception()
