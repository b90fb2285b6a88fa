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

`Machine` is one class written in layers, a file each, as the engine is: a
layer calls only itself and the layers below it; where a lower layer must
reach an upper one it declares a hook (raising NotImplementedError):

  machine_core.py        MachineCore        every field; serve, connect and
                                            disconnect; the supervisor
                                            following the engine; the faults
                                            and `reset`; the hooks
                                            `_begin_operation`,
                                            `_operation_stopped` (the
                                            operations') and `_tool_changer`
                                            (Machine's)
  machine_operations.py  MachineOperations  make jobs, programs, jogs and
                                            settings batches, and the board's
                                            settings, limits and offsets
  machine.py             Machine            the commands the API gives, a
                                            job's pause, resume and cancel,
                                            its tool changes; the views

This module keeps `Machine` and `NoSuchFile` where every importer finds them.
"""

from __future__ import annotations

import asyncio
from typing import Any, Final

from hostd.machine.jobfile import NoSuchFile
from hostd.machine.jobstore import Job, ToolChange
from hostd.machine.machine_operations import MachineOperations
from hostd.machine.stream import JobStream
from hostd.machine.supervisor import Event as SupEvent
from hostd.machine.supervisor import State as SupState
from hostd.machine.toolchange import ToolChanger
from hostd.protocol.commands import Realtime
from hostd.protocol.errors import Busy, MachineError
from hostd.protocol.messages import Response

# Seconds the daemon's stop waits for a running job's kill to bring its board to rest
# (a few times a hold's deceleration; the unit's TimeoutStopSec is 20).
SHUTDOWN_STOP_WAIT: Final = 5.0

__all__ = ["Machine", "NoSuchFile"]


class Machine(MachineOperations):
    """One configured machine, and the only way down to its engine (see the module)."""

    def _tool_changer(self) -> ToolChanger:
        return ToolChanger(self)

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
        works inside it), still through the command-class admission. A line that moves
        the machine or starts its spindle or beam is refused (1007) while a fault that
        blocks a job is active, as a jog is."""
        self.refuse_line_if_faulted(line)
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

    async def stop_for_shutdown(self, wait: float = SHUTDOWN_STOP_WAIT) -> None:
        """The daemon is stopping: a job still streaming ends interrupted (1002) and is
        killed on the board as a cancel kills it, and the board's stop is awaited for at
        most `wait` seconds, so that its port closes on a board at rest with its spindle
        off, not one running the job's lines unwatched."""
        stream = self._live_stream()
        if stream is None:
            return
        try:
            self.engine.interrupt_stream(
                1002, "the daemon stopped during the job (it stopped the board as a cancel does)"
            )
        except MachineError:
            return  # the link is gone: nothing can reach the board
        session = self.engine.session
        try:
            async with asyncio.timeout(wait):
                await asyncio.shield(stream.result)
                # Its row's end written and told before the machine's tasks are cancelled,
                # as a cancel waits for it: a follower cancelled mid-end told nobody.
                await self.jobs.followed(timeout=wait)
                await self.engine.wait_for(lambda: not session.flushing())
        except (TimeoutError, MachineError):
            # A board that does not answer, or a grbl held rather than reset (a startup
            # block that moves): it may still hold the job's lines.
            self._log.warning("the board did not show its stop before the daemon stopped")

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
            self.engine.release_stream(change.tool)
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
            occupied=self.engine.session.occupied(),
            faults=[f.to_json() for f in self.faults.active()],
            job=self.jobs.current_json(),
            tool_change=self.tools.snapshot(),
            position_units=self._position_units(),
        )
        return snap

    def _position_units(self) -> dict[str, str]:
        """What `machine_position` and `work_position` are in, as the board reports them
        (`position_scales`): not always `units`, the units mode, which g2core's machine
        position and grbl's both positions do not follow."""
        machine, work = self.engine.session.position_scales()
        return {"machine": "mm" if machine == 1.0 else "in", "work": "mm" if work == 1.0 else "in"}
