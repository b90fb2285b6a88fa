"""One configured machine: its engine, its supervisor, its faults and its operations.

The supervisor follows the engine: the link coming up is `connect`, going
down `disconnected` (or `disconnect` when asked for), and every status
report settles busy against idle. Operations (`make`, `jog`, `settings`)
start only from idle, each recorded as a job row by the job runner
(jobrunner.py); `make` streams a file from the jobs directory and is the
only pausable one.

The engine tells the Machine everything through one callback; the Machine
publishes each fact to the hub before what it causes. The Machine's task
(`serve`) owns a task group: the engine's connection runs in it, and so
does the follower of every streaming job; it returns only once they all have.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, TextIO

import structlog

from hostd.machine.config import MachineConfig
from hostd.machine.engine import Engine
from hostd.machine.events import (
    EngineEvent,
    FaultChanged,
    FaultDetected,
    Hub,
    LinkChanged,
    StatusChanged,
    SupervisorChanged,
)
from hostd.machine.faults import Fault, FaultTable
from hostd.machine.jobrunner import JobRunner
from hostd.machine.jobstore import Job, JobStore, ToolChange
from hostd.machine.signals import fault_conditions
from hostd.machine.stream import JobStream
from hostd.machine.supervisor import Event as SupEvent
from hostd.machine.supervisor import State as SupState
from hostd.machine.supervisor import Supervisor, Transition
from hostd.machine.toolchange import ToolChanger
from hostd.protocol.commands import InvalidCommand, Realtime
from hostd.protocol.errors import Busy, FaultActive, MachineError
from hostd.protocol.gcodestate.resume import Board
from hostd.protocol.limits import MachineLimits
from hostd.protocol.messages import Response
from hostd.protocol.program import program_blocks, program_lines
from hostd.protocol.states import MachineState
from hostd.protocol.vocabulary import StreamEnd, StreamResult

log = structlog.get_logger(__name__)


class NoSuchFile(MachineError):
    code = 1004


class Machine:
    def __init__(
        self,
        config: MachineConfig,
        store: JobStore,
        jobs_dir: Path,
        *,
        hub: Hub | None = None,
    ) -> None:
        self.config = config
        self.id = config.id
        self.store = store
        self.jobs_dir = jobs_dir
        self.hub = hub or Hub()
        self.engine = Engine(config, self._on_engine)
        self.supervisor = Supervisor(self._on_transition)
        self.jobs = JobRunner(
            self.id,
            self.engine,
            store,
            self.hub,
            begin_operation=self._begin_operation,
            end_operation=self._operation_stopped,
        )
        self.faults = FaultTable()
        self._signal_values: dict[str, Any] = {}  # the last value of every signal key
        self._signals: dict[str, bool] = {}
        self._disconnect_asked = False
        self.tools = ToolChanger(self)  # the job's M6s, by the tool_change policy
        self._log = log.bind(machine=self.id)

    # -- lifecycle ---------------------------------------------------------

    async def serve(self) -> None:
        """Run the engine and every streaming job's follower until cancelled.

        They live in one task group: cancelled, it cancels the followers (each
        writes its job's end) and returns only once every one has.
        """
        async with asyncio.TaskGroup() as group:
            with self.jobs.serving(group):
                await self.engine.serve()

    @property
    def job(self) -> Job | None:
        """The current or last operation's row."""
        return self.jobs.job

    async def connect(self) -> None:
        self._disconnect_asked = False
        await self.engine.connect()

    async def disconnect(self) -> None:
        self._disconnect_asked = True
        await self.engine.disconnect()

    # -- the supervisor follows the engine --------------------------------

    def _on_engine(self, event: EngineEvent) -> None:
        """The engine's one way up. A fact is published before what it causes: a status
        report before the supervisor change and the faults it brings (clients read them
        in that order). A fault the engine detected is the fault table's to decide."""
        if isinstance(event, FaultDetected):
            now_ = time.time()
            self._fault_changed(
                self.faults.raise_(event.fault, value=event.value, message=event.message, now=now_)
            )
            return
        self.hub.publish(event)
        if isinstance(event, LinkChanged):
            if event.up and self.supervisor.can(SupEvent.CONNECT):
                self.supervisor.fire(SupEvent.CONNECT)
            elif not event.up and self.supervisor.state is not SupState.DISCONNECTED:
                asked = self._disconnect_asked
                self.supervisor.fire(SupEvent.DISCONNECT if asked else SupEvent.DISCONNECTED)
            self._settle()
        elif isinstance(event, StatusChanged):
            self._on_signals(event.report)
            self._settle()

    def _settle(self) -> None:
        """Busy against idle, from what the board says and what the host has queued."""
        state = self.engine.model.state
        resting = (
            self.engine.ready and state is not None and state.is_resting and self.engine.quiet()
        )
        if self.supervisor.state is SupState.BUSY and resting:
            self.supervisor.fire(SupEvent.WENT_IDLE)
        elif self.supervisor.state is SupState.IDLE and not resting:
            self.supervisor.fire(SupEvent.WENT_BUSY)

    def _on_transition(self, t: Transition) -> None:
        self._log.info("supervisor", source=t.source.value, target=t.target.value, on=t.event.value)
        # From start-operation to operation-stopped no client action fits (1003), even
        # before the job streams or while a settings batch or a jog runs.
        self.engine.set_operation(t.target in (SupState.OPERATION, SupState.PAUSED))
        self.hub.publish(SupervisorChanged(self.id, t.source.value, t.target.value, t.event.value))

    # -- faults ------------------------------------------------------------

    def _on_signals(self, report: dict[str, Any]) -> None:
        """Signals from the report's keys (it carries only changes), then the fault rules."""
        signals = self.config.signals
        keys = signals.keys()
        self._signal_values.update((k, v) for k, v in report.items() if k in keys)
        self._signals = signals.evaluate(self._signal_values, self._signals)
        conditions = fault_conditions(self._signals)
        # The controller's SHUTDOWN (its e-stop input) is always an e-stop source.
        shutdown = self.engine.model.state is MachineState.SHUTDOWN
        conditions["estop"] = conditions.get("estop", False) or shutdown
        now_ = time.time()
        for fault_id, active in conditions.items():
            self._fault_changed(self.faults.set(fault_id, active, now=now_))

    def _fault_changed(self, fault: Fault | None) -> None:
        """Publish a change and apply its effect on a running job."""
        if fault is None:
            return
        self._log.warning("fault", fault=fault.id, active=fault.active, value=fault.value)
        self.hub.publish(FaultChanged(self.id, fault.to_json()))
        blocking = self.faults.blocking()
        if blocking and self.jobs.live() is not None:
            ids = ", ".join(f.id for f in blocking)
            self.engine.stop_stream(FaultActive.code, f"fault active: {ids}")

    def override_fault(self, fault_id: str, on: bool) -> Fault:
        fault = self.faults.override(fault_id, on)
        self._fault_changed(fault)
        return fault

    def clear_fault(self, fault_id: str) -> Fault:
        before = self.faults.get(fault_id)
        fault = self.faults.clear(fault_id)
        if fault != before:
            self._fault_changed(fault)
        return fault

    def _refuse_if_faulted(self) -> None:
        blocking = self.faults.blocking()
        if blocking:
            ids = [f.id for f in blocking]
            raise FaultActive(f"{self.id}: fault active: {', '.join(ids)}", ids)

    async def reset(self) -> None:
        """0x18 and re-synchronisation; the back end's own faults are cleared with it."""
        await self.engine.reset()
        for fault in self.faults.reset():
            self._fault_changed(fault)

    # -- operations ----------------------------------------------------------

    async def start_make(
        self,
        file: str,
        start_line: int = 1,
        preamble: list[str] | None = None,
        *,
        counted: int | None = None,
    ) -> Job:
        """Stream a file of the jobs directory (its name is checked by the API layer).

        `preamble`: lines sent first, before `start_line` (a resume's restore and
        approach, hostd.protocol.gcodestate.resume); they are file line 0, and the row
        keeps them. Every line goes with its file line number as an N word. `counted`:
        the file's sendable lines from `start_line`, if the job's check just counted
        them on a worker (preflight.prepare_start); else they are counted here.
        """
        path = self.jobs_dir / file
        if not await asyncio.to_thread(path.is_file):
            raise NoSuchFile(f"no file {file!r} in the jobs directory")
        total = counted
        if total is None:
            total = await asyncio.to_thread(_count_lines, path, start_line)
        before = [(0, line) for line in preamble or ()]
        handle = path.open(encoding="utf-8", errors="replace")
        try:
            lines = itertools.chain(before, program_lines(handle, start_line))
            return await self._start_make(
                file,
                total + len(before),
                lines,
                handle,
                start_line=start_line if start_line > 1 or preamble else None,
                preamble=preamble,
            )
        except BaseException:
            handle.close()
            raise

    async def start_program(self, lines: list[str]) -> Job:
        """Lines the daemon made (a macro's, a frame's), run as a make job with no file:
        admitted, numbered, paused, resumed and cancelled as any make job. The caller has
        checked the lines as a file's are checked (hostd/machine/macros.py)."""
        return await self._start_make(None, len(lines), enumerate(lines, start=1), None)

    async def _start_make(
        self,
        file: str | None,
        total: int,
        lines: Iterator[tuple[int, str]],
        handle: TextIO | None,
        *,
        start_line: int | None = None,
        preamble: list[str] | None = None,
    ) -> Job:
        """A make job, its M6s read by the tool-change policy (toolchange.py)."""
        lines = self.tools.lines(lines)
        holds = self.tools.holds(lines)
        job = await self.jobs.start(
            "make",
            file,
            total,
            lines,
            handle,
            start_line=start_line,
            preamble=preamble,
            holds=holds,
        )
        if holds is not None:
            self.tools.follow(self.jobs.live(), holds)
        return job

    async def jog(self, axes: dict[str, float], feed: float) -> Job:
        lines = self.engine.session.jog_lines(axes, feed)
        if self.tools.holding() and self.job is not None:
            if not self.tools.operator_may_move():
                raise Busy(f"{self.id} is measuring the new tool: wait until it is done")
            # A job waits at a tool change: the jog is its own lines, no operation of its own.
            self.tools.operator_acted()
            for line in lines:
                await self.engine.send(line, operation=True)
            return self.job
        # g2core jogs in G-code and puts G90 back as its last line; a stopped jog needs it too.
        restore = lines[-1] if len(lines) > 1 else None
        return await self.jobs.start(
            "jog", None, len(lines), enumerate(lines, start=1), None, if_stopped=restore
        )

    async def read_settings(self, keys: list[str]) -> dict[str, Any]:
        """Read settings: queries, so served in every state while the link is up; no job row."""
        session = self.engine.session
        lines = session.settings_read(keys)
        answers = await asyncio.gather(*(self.engine.send(line) for line in lines))
        return session.settings_found(keys, [response.body for response in answers])

    async def limits(self) -> MachineLimits:
        """Travel, traverse rates and accelerations, from the board's settings (its dialect's)."""
        session = self.engine.session
        return session.machine_limits(await self.read_settings(session.limit_settings()))

    async def board_offsets(self) -> Board:
        """The board's stored offsets (G54..), its G92 and spindle speed, in mm: what a
        resume plans from (hostd.protocol.gcodestate.resume). Queries: any state."""
        session = self.engine.session
        answers = await asyncio.gather(*(self.engine.send(q) for q in session.offset_reads()))
        return session.board_offsets([response.body for response in answers])

    def safe_height(self, limits: MachineLimits | None) -> float | None:
        """`safe_z` from the config, else the top of the Z travel (mm, machine coordinates).

        The travel's top is a place only once the machine is homed: before, machine
        coordinates count from wherever the board was switched on, and `G53 G0 Z<top>`
        could drive Z down to that height, or up into its end stop. Unhomed and without
        `safe_z`, the safe height is unknown (None), and whoever needs it refuses.
        """
        if self.config.safe_z is not None:
            return self.config.safe_z
        homed = self.snapshot().get("homed") is True
        if homed and limits is not None and "z" in limits.travel:
            return limits.travel["z"][1]
        return None

    async def write_settings(
        self, values: dict[str, bool | int | float | str]
    ) -> tuple[Job, list[dict[str, Any]]]:
        """`settings` with the lines the board's dialect writes these values with."""
        return await self.settings(self.engine.session.settings_write(values))

    async def settings(self, lines: list[str]) -> tuple[Job, list[dict[str, Any]]]:
        """A batch of settings lines run as one operation; the bodies the board answered.

        The row says `completed` only when every line was answered with
        status 0; anything else, even the request being abandoned, is `failed`.
        """
        job = await self.jobs.begin("settings", None, len(lines))
        bodies: list[dict[str, Any]] = []
        result = StreamResult(StreamEnd.FAILED, 1005, "the settings operation was abandoned")
        try:
            for line in lines:
                response = await self.engine.send(line, operation=True)
                bodies.append(response.body)
                await self.jobs.save(lines_sent=len(bodies), lines_acked=len(bodies))
            result = StreamResult(StreamEnd.COMPLETED)
        except MachineError as exc:
            result = StreamResult(StreamEnd.FAILED, exc.code, exc.message)
            raise
        except InvalidCommand as exc:
            result = StreamResult(StreamEnd.FAILED, -32602, exc.message)
            raise
        finally:
            await asyncio.shield(self.jobs.end(result))
        return job, bodies

    def _begin_operation(self) -> None:
        """An operation may begin: a locked-out board is the first thing to say
        (204/205/206), then a fault (1007), then "busy" (1003, unless idle)."""
        self.engine.admit_action()
        self._refuse_if_faulted()
        self.supervisor.fire(SupEvent.START_OPERATION)

    def _operation_stopped(self) -> None:
        if self.supervisor.can(SupEvent.OPERATION_STOPPED):
            self.supervisor.fire(SupEvent.OPERATION_STOPPED)
        self._settle()

    # -- commands the API gives: the machine is the only way down ------------

    @property
    def console(self) -> bool:
        """Whether the engine publishes every line sent and received (someone listens)."""
        return self.engine.console

    @console.setter
    def console(self, listening: bool) -> None:
        self.engine.console = listening

    @property
    def console_but_job(self) -> bool:
        """Whether the engine publishes every line but a running job's own and their plain
        answers (someone listens to the console without them)."""
        return self.engine.console_but_job

    @console_but_job.setter
    def console_but_job(self, listening: bool) -> None:
        self.engine.console_but_job = listening

    @property
    def console_status(self) -> bool:
        """Whether the engine publishes status polls and reports among the console's
        lines (someone listens with them)."""
        return self.engine.console_status

    @console_status.setter
    def console_status(self, listening: bool) -> None:
        self.engine.console_status = listening

    async def send(self, line: str, timeout: float = 10.0) -> Response:
        """One line, through the same admission as any other; its answer.

        While a job waits at a tool change the line goes as the job's own (the operator
        works inside it), still through the command-class admission."""
        if self.tools.holding() and not self.tools.operator_may_move():
            raise Busy(f"{self.id} is measuring the new tool: wait until it is done")
        if self.tools.holding():
            self.tools.operator_acted()
        return await self.engine.send(line, timeout=timeout, operation=self.tools.holding())

    def realtime(self, command: Realtime) -> None:
        """A realtime command: written ahead of every queued line."""
        self.engine.realtime(command)

    async def clear(self) -> None:
        """End a lockout the way the controller allows (the dialect's clear)."""
        await self.engine.clear()

    async def alarm(self) -> None:
        """Raise the controller's alarm (refused where the dialect has none)."""
        await self.engine.alarm()

    async def shutdown(self) -> None:
        """The controller's shutdown (refused where the dialect has none)."""
        await self.engine.shutdown()

    def safety_door(self) -> None:
        """The safety-door realtime command, where the dialect has one."""
        self.engine.safety_door()

    # -- pause, resume, cancel ---------------------------------------------

    def jog_stop(self) -> None:
        """Feedhold, then queue flush (seed 002's jog stop): the rest of the move is dropped."""
        if self.tools.holding():
            # The flush would end the waiting job too (it is the job's cancel on both dialects).
            raise Busy(
                f"{self.id} waits at a tool change: jog by distances, or machine.feedhold "
                "to stop a jog (a queue flush would cancel the job)"
            )
        self.engine.realtime(Realtime.FEEDHOLD)
        self.engine.realtime(Realtime.QUEUE_FLUSH)

    def feedhold(self) -> None:
        """`!`; during a make job it is the job's pause."""
        if self._pausable():
            self.pause()
        else:
            self.engine.realtime(Realtime.FEEDHOLD)

    def cycle_start(self) -> None:
        """`~`; while paused it is the job's resume (but at a tool change, where it only
        lets a jog the operator held go on: job.tool_change_done goes past the M6)."""
        if self._resumable() and not self.tools.holding():
            self.resume()
        else:
            self.engine.realtime(Realtime.CYCLE_START)

    def pause(self) -> Job:
        """Pause the streaming make job: `!`, and none of its lines written until resumed.

        Only the job that is streaming can be paused: one whose stream has
        ended is final, even while its row is still being written.
        """
        if not self._pausable():
            raise Busy(f"{self.id} has no running make job to pause")
        self.engine.pause_stream()
        self.supervisor.fire(SupEvent.PAUSE_OPERATION)
        return self._set_job_state("paused")

    def resume(self) -> Job:
        if self.tools.holding():
            raise Busy(f"{self.id} waits at a tool change: answer it with job.tool_change_done")
        if not self._resumable():
            raise Busy(f"{self.id} has no paused job to resume")
        with self.engine.one_step():  # no job line goes out while the supervisor says paused
            self.engine.resume_stream()
            self.supervisor.fire(SupEvent.UNPAUSE_OPERATION)
        return self._set_job_state("running")

    async def cancel(self) -> Job:
        """0x04: the board kills the job; the host drops what it had not sent."""
        stream = self._live_stream()
        if stream is None or self.job is None:
            raise Busy(f"{self.id} has no running job to cancel")
        cancelled = self.job.id
        self.engine.realtime(Realtime.JOB_KILL)
        async with asyncio.timeout(5):
            await asyncio.shield(stream.result)
        await self.jobs.followed(timeout=5)  # let the row reach its end state
        if self.job.id == cancelled:
            return self.job
        # Another client started a job once this one ended: answer for the one cancelled
        # (its row is on disk: the end is told only once written).
        return await self.store.get(cancelled) or self.job

    def _live_stream(self) -> JobStream | None:
        """The stream of the running operation, while it streams; None once it ended."""
        return self.jobs.live()

    def _pausable(self) -> bool:
        return (
            self.supervisor.state is SupState.OPERATION
            and self._live_stream() is not None
            and self.job is not None
            and self.job.kind == "make"
        )

    def _resumable(self) -> bool:
        return self.supervisor.state is SupState.PAUSED and self._live_stream() is not None

    # -- tool changes (hostd/machine/toolchange.py) --------------------------

    async def tool_change_done(self) -> Job:
        """The operator changed the tool: record it and go on (1003 if none is waited for)."""
        await self.tools.done()
        return self.current_job() or self._no_job()

    def _no_job(self) -> Job:
        raise Busy(f"{self.id} has no job")

    def tool_change_held(self) -> None:
        """The job holds at an M6, the board at rest: paused, until the operator answers."""
        if self.supervisor.can(SupEvent.PAUSE_OPERATION):
            self.supervisor.fire(SupEvent.PAUSE_OPERATION)
        if self._live_stream() is not None:
            self._set_job_state("paused")

    def tool_change_answered(self, stream: JobStream, change: ToolChange) -> None:
        """Record the change; the job goes on with the M6 line, in one step."""
        assert self.job is not None
        changes = [*self.job.tool_changes, change]
        with self.engine.one_step():  # no job line goes out while the supervisor says paused
            self.engine.release_stream()
            if stream.paused:  # the user's `!` too: its `~`
                self.engine.resume_stream()
            if self.supervisor.can(SupEvent.UNPAUSE_OPERATION):
                self.supervisor.fire(SupEvent.UNPAUSE_OPERATION)
        if self._live_stream() is not None:
            self.jobs.change(state="running", tool_changes=changes)

    def _set_job_state(self, state: str) -> Job:
        """Only ever called while the job streams: a job's end state is final."""
        assert self.job is not None and self._live_stream() is not None
        return self.jobs.change(state=state)

    # -- views -------------------------------------------------------------

    def current_job(self) -> Job | None:
        return self.jobs.current()

    def is_laser(self) -> bool:
        """The tool is a laser: the config says so, or the board is in laser mode."""
        return self.config.laser or self.engine.model.laser_mode is True

    def snapshot(self) -> dict[str, Any]:
        snap = self.engine.model.snapshot()
        if snap["laser_mode"] is None and self.config.laser:
            # A board that cannot say (g2core: its laser toolhead is chosen when the
            # firmware is built, HAS_LASER): the config's word.
            snap["laser_mode"] = True
        snap.update(
            dialect=self.config.dialect,
            supervisor=self.supervisor.state.value,
            indicator=self.faults.indicator().value,
            lockout=self.engine.session.lockout(),
            faults=[f.to_json() for f in self.faults.active()],
            job=self.jobs.current_json(),
            tool_change=self.tools.snapshot(),
        )
        return snap


def _count_lines(path: Path, start_line: int) -> int:
    with path.open(encoding="utf-8", errors="replace") as f:
        return sum(map(len, program_blocks(f, start_line)))  # a block at a time, not a line


def setting_lines(values: dict[str, Any]) -> list[str]:
    """One SET line a setting: the board answers each with the value it stored."""
    return [json.dumps({key: value}, separators=(",", ":")) for key, value in values.items()]
