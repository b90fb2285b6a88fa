"""The Machine's core: its fields, its lifecycle, the supervisor following the
engine, and the fault table.

The lowest layer of `Machine` (machine.py lists the layers). The engine tells
the Machine everything through one callback (`_on_engine`); the Machine
publishes each fact to the hub before what it causes. The Machine's task
(`serve`) owns a task group: the engine's connection runs in it, and so
does the follower of every streaming job; it returns only once they all have.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import structlog

from hostd.machine.config import MachineConfig
from hostd.machine.engine import Engine
from hostd.machine.events import (
    BoardOccupied,
    EngineEvent,
    FaultChanged,
    FaultDetected,
    Hub,
    JobChanged,
    LinkChanged,
    StatusChanged,
    SupervisorChanged,
)
from hostd.machine.faults import Fault, FaultTable
from hostd.machine.jobrunner import JobRunner
from hostd.machine.jobstore import Job, JobStore
from hostd.machine.signals import fault_conditions, fault_readings
from hostd.machine.supervisor import Event as SupEvent
from hostd.machine.supervisor import State as SupState
from hostd.machine.supervisor import Supervisor, Transition
from hostd.protocol.errors import FaultActive
from hostd.protocol.states import MachineState

if TYPE_CHECKING:
    from hostd.machine.toolchange import ToolChanger

log = structlog.get_logger(__name__)


class MachineCore:
    """Every field, the lifecycle, the supervisor and the faults (see `Machine`)."""

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
        # An operation of ours ended without its end reaching the board (the daemon died,
        # the link was lost): what the board is found doing at the next connect is checked.
        self._unwatched: tuple[str, int | None] | None = None  # why, and the job's id
        # The task of an operation that moves or powers (operations.py), while it runs,
        # and the 1007 it ends with once a fault stopped it (`_stop_powered_operation`).
        self.powered_operation: asyncio.Task[Any] | None = None
        self.operation_fault: FaultActive | None = None
        self._group: asyncio.TaskGroup | None = None  # `serve`'s, while it runs
        self._log = log.bind(machine=self.id)
        self.tools = self._tool_changer()  # the job's M6s, by the tool_change policy

    # -- lifecycle ---------------------------------------------------------

    async def serve(self) -> None:
        """Run the engine and every streaming job's follower until cancelled.

        They live in one task group: cancelled, it cancels the followers (each
        writes its job's end) and returns only once every one has.
        """
        async with asyncio.TaskGroup() as group:
            self._group = group
            try:
                with self.jobs.serving(group):
                    await self.engine.serve()
            finally:
                self._group = None

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
        if isinstance(event, BoardOccupied):
            self._stop_unwatched()  # if it was left running: else the handshake waits
            return
        self.hub.publish(event)
        if isinstance(event, LinkChanged):
            if event.up and self.supervisor.can(SupEvent.CONNECT):
                self.supervisor.fire(SupEvent.CONNECT)
                self._stop_unwatched()
            elif not event.up and self.supervisor.state is not SupState.DISCONNECTED:
                if self.supervisor.state in (SupState.OPERATION, SupState.PAUSED):
                    job = self.job
                    self.ran_unwatched(
                        f"an operation was under way when the link went: {event.reason}",
                        job.id if job is not None and job.kind == "make" else None,
                    )
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

    # -- a board left running -------------------------------------------------

    def ran_unwatched(self, why: str, job: int | None = None) -> None:
        """An operation of ours ended without its end reaching the board: the daemon died
        during it (`Daemon.run` passes the rows it recovered) or the link was lost. The
        board ran on with what it held, and may still be running it, or stand with the
        spindle or beam the operation left on; at the next connect it is stopped if so
        (`_stop_unwatched`). `job`: the make job that was under way, whose row then
        learns how far the board got (`_note_line_reached`)."""
        self._unwatched = (why, job)

    def _stop_unwatched(self) -> None:
        """At a connect after `ran_unwatched`, or sooner where the handshake waits on a
        board busy with its moves (`BoardOccupied`: grbl reads no line until they end):
        a board still moving or holding moves (not at rest, not in a lockout, which
        drained it), or standing with its spindle on, gets the dialect's job kill, as a
        cancel would (docs/operations.md, "When the daemon stops"). Nobody is watching
        those lines, and the job that sent them is already interrupted; a board at rest
        with its spindle off is left as it is."""
        unwatched, self._unwatched = self._unwatched, None
        model = self.engine.model
        state = model.state
        if unwatched is None or state is None:
            return
        why, job = unwatched
        if state.is_lockout:
            return
        spindle = (model.spindle or {}).get("state")
        if state.is_resting and spindle not in ("cw", "ccw"):
            return
        line = self.engine.session.line_running()
        if job is not None and not state.is_resting and line is not None:
            assert self._group is not None  # a link comes up only while `serve` runs
            self._group.create_task(self._note_line_reached(job, line))
        self._log.warning(
            "stopping the board: it ran on unwatched",
            why=why,
            state=state.name,
            spindle=spindle,
        )
        self.engine.kill_job()

    async def _note_line_reached(self, job_id: int, line: int) -> None:
        """The board ran on past the interrupted job's `line_executed` (written at most 1 s
        or 100 lines apart, and never after the daemon died or the link went): the line
        its first report says it is executing (the dialect's word, `line_running`), found
        still moving, is where a resume begins, not lines it already ran (a laser would
        burn them twice). Only then: at rest, or in a hold on g2core, a board reports the
        last line it read, which something may have flushed unrun. Only ever forward,
        and only on a row that numbers its lines (it has a `line_executed`)."""
        try:
            row = await self.store.get(job_id)
            if row is None or row.state != "interrupted" or row.line_executed is None:
                return
            if line <= row.line_executed:
                return
            updated = await self.store.update(job_id, line_executed=line)
        except Exception:  # in `serve`'s group: a failed write must not end the machine
            self._log.exception("interrupted job: its line could not be written", job=job_id)
            return
        self._log.info(
            "interrupted job: the board got further", job=job_id, line=line, was=row.line_executed
        )
        self.hub.publish(JobChanged(self.id, updated.model_dump(mode="json")))

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
        readings = fault_readings(signals, self._signal_values)
        now_ = time.time()
        for fault_id, active in conditions.items():
            # A coolant fault's value is the reading that raised it, kept while it lasts: a
            # reading that moves every report would otherwise be a change told each time.
            fault = self.faults.get(fault_id)
            value = fault.value if fault.active else readings.get(fault_id)
            self._fault_changed(self.faults.set(fault_id, active, value=value, now=now_))

    def _fault_changed(self, fault: Fault | None) -> None:
        """Publish a change and apply its effect on a running job, or on an operation that
        moves the machine or powers its spindle or beam."""
        if fault is None:
            return
        self._log.warning("fault", fault=fault.id, active=fault.active, value=fault.value)
        self.hub.publish(FaultChanged(self.id, fault.to_json()))
        blocking = self.faults.blocking()
        if not blocking:
            return
        ids = [f.id for f in blocking]
        if self.jobs.live() is not None:
            self.engine.stop_stream(FaultActive.code, f"fault active: {', '.join(ids)}")
        self._stop_powered_operation(ids)

    def _stop_powered_operation(self, ids: list[str]) -> None:
        """A fault that blocks a job, become active while an operation moves the machine or
        powers its spindle or beam (a test-fire, a go-to-zero, a homing, a probe): the
        board gets the dialect's job kill, as a stopped job's board does, and the
        operation's task is cancelled; it ends with this 1007 (operations.py)."""
        task = self.powered_operation
        if task is None or task.done() or self.operation_fault is not None:
            return
        self.operation_fault = self._fault_active(ids)
        self._log.warning("stopping the operation: a fault is active", faults=ids)
        self.engine.kill_job()
        task.cancel()

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

    def refuse_line_if_faulted(self, line: str) -> None:
        """1007 for a line a client sends (machine.send, machine.maintenance) that moves
        the machine or starts its spindle or beam (the dialect's `powered`) while a fault
        that blocks a job is active and not overridden, as a jog is refused."""
        blocking = self.faults.blocking()
        does = self.config.spec.powered(line) if blocking else None
        if does is not None:
            ids = [f.id for f in blocking]
            why = f": the line {does}; clear or override the fault first"
            raise self._fault_active(ids, why)

    def refuse_if_faulted(self) -> None:
        """1007 while a fault that blocks a job is active and not overridden: for a job,
        a jog, a settings batch, and an operation that moves or powers (operations.py)."""
        blocking = self.faults.blocking()
        if blocking:
            raise self._fault_active([f.id for f in blocking])

    def _fault_active(self, ids: list[str], why: str = "") -> FaultActive:
        """The 1007 for these blocking faults (`data`: their ids)."""
        return FaultActive(f"{self.id}: fault active: {', '.join(ids)}{why}", ids)

    async def reset(self) -> None:
        """0x18 and re-synchronisation; the back end's own faults are cleared with it."""
        await self.engine.reset()
        for fault in self.faults.reset():
            self._fault_changed(fault)

    # -- the upper layers' hooks ------------------------------------------------

    def _tool_changer(self) -> ToolChanger:
        """`Machine`'s: the tool changer works through the whole machine (it holds and
        releases the job, jogs, probes)."""
        raise NotImplementedError

    def _begin_operation(self) -> None:
        """The job runner's: an operation may begin, or this raises why not."""
        raise NotImplementedError

    def _operation_stopped(self) -> None:
        """The job runner's: the operation's row has reached its end."""
        raise NotImplementedError
