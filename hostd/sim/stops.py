"""Everything that stops the simulated g2core's motion: holds, flush, kill and lockouts.

The layer of `Board` (board.py) above its intake (intake.py): the realtime
controls, feedhold and its exits (resume, queue flush, job kill) [8], the
lockouts ALARM, SHUTDOWN and PANIC and their clearing [10], and the end of a
probing cycle. They are one layer because the firmware makes them one: from
101.05 an alarm is a feedhold whose exit action kills the job and locks
(alarm.cpp cm_alarm, cycle_feedhold.cpp `_run_alarm`), from 101.02 a ^D in
a moving cycle is a hold with the kill pending, a flush or a lockout ends a probing
cycle (`cm_abort_probing`), and a probe that never trips raises an alarm.
Each calls the others, so none of them can sit below the rest. How each
build differs is on `self.build` (g2builds.py); the planner that runs the
blocks is above, in planner.py, and also starts the probing cycle.
"""

from __future__ import annotations

import structlog

from hostd.protocol.states import MachineState
from hostd.protocol.status import Status
from hostd.sim.config import AXES
from hostd.sim.intake import Intake
from hostd.sim.output import Hold
from hostd.sim.probing import PROBE_AXES

log = structlog.get_logger(__name__)

ENQ, JOB_KILL, RESET = 0x05, 0x04, 0x18
_LOCKOUT_EXITS = ("alarm", "shutdown")  # a hold's exit that makes a lockout (101.05+)

_REJECTED_BY = {
    MachineState.ALARM: Status.COMMAND_REJECTED_BY_ALARM,
    MachineState.SHUTDOWN: Status.COMMAND_REJECTED_BY_SHUTDOWN,
    MachineState.PANIC: Status.COMMAND_REJECTED_BY_PANIC,
}


class Stops(Intake):
    """The holds, flush, kill and lockouts that stop the planner, and a probe's end."""

    # --- feedhold, resume, flush, kill [8, seed 002]

    def realtime(self, port: str, char: int, mark: int | None = None) -> None:
        """A single-character control [8], as controller.cpp `_dispatch_kernel` runs it.
        `mark`: the port's data lines that came in before it (None: all there are)."""
        now = self._clock()
        self._control_read(port, mark)
        if char == ord("!"):
            self._feedhold(now)
        elif char == ord("~"):
            self._cycle_start()
        elif char == ord("%"):
            self._queue_flush(now)  # cm_request_queue_flush(); xio_flush_to_command()
            self._flush_to_command()
        elif char == JOB_KILL:
            if self.build.kill_alarms:
                # Before 101.02 ^D is an alarm, and nothing is flushed (100.26 controller.cpp:259).
                self._lockout(MachineState.ALARM, Status.KILL_JOB, "EOT Received")
            else:
                self._job_kill(now)  # cm_request_job_kill(); xio_flush_to_command()
                self._flush_to_command()
        elif char == ENQ:
            self._emit({"ack": True})
        elif char == RESET:
            self._request_reset()
        self._flush_sr()

    def _feedhold(self, now: float) -> None:
        active = self.active
        if self.hold != Hold.OFF or self.state.is_lockout:
            return  # a new request is ignored unless the hold is off
        if self.state != MachineState.RUN:
            if self.build.hold_at_rest and self.state != MachineState.INTERLOCK:
                # edge-preview `_feedhold_with_actions`: with the runtime idle the hold is
                # in place at once; the machine is not in a cycle, so `stat` stays.
                self.hold = Hold.HOLD
                self._hold_point = dict(self.position)
                self._sr_now = True
            return  # 100.26 and 101.03 honour `!` only while moving
        self._set_state(MachineState.HOLD)
        if active is None:
            # The cycle's first move has not started (the planner primes): the runtime is
            # idle, so the hold is in place at once (_feedhold_with_actions).
            self._enter_hold(now, at=now)
            return
        active.begin_hold(now, self.config.feedhold_decel)
        self.hold = Hold.DECEL

    def _hold_reached(self, now: float) -> None:
        assert self.active is not None
        self._enter_hold(now, at=self.active.end)

    def _enter_hold(self, now: float, *, at: float) -> None:
        """The tool stands still (at time `at`): the hold is in place, deferred exits run."""
        self._halt(at)
        self.hold = Hold.HOLD
        self._hold_point = dict(self.position)
        self._sr_now = True
        pending, self._pending_exit = self._pending_exit, None
        if pending == "resume":
            self._cycle_start()
        elif pending == "flush":
            self._queue_flush(now)
        elif pending == "kill":
            self._job_kill(now)
        elif pending in ("alarm", "shutdown"):
            self._alarm_held(now, pending)

    def _leave_hold(self) -> None:
        if self._hold_point is not None:
            self.position = self._hold_point  # the return move to the hold point
        self.hold = Hold.OFF
        self._hold_point = None
        self._p2 = None

    def _cycle_start(self) -> None:
        if self._pending_exit in _LOCKOUT_EXITS:
            return  # the alarm's own hold ends in its exit action, not in a restart
        if self.hold == Hold.DECEL:
            self._pending_exit = "resume"
            return
        if self.hold != Hold.HOLD or self.interlocked:
            return
        at_rest = self.state != MachineState.HOLD  # a hold taken at rest (101.05+)
        self._leave_hold()
        if at_rest:
            self._sr_now = True
            return
        self._set_state(MachineState.RUN if self.planner else MachineState.PROGRAM_STOP)

    def _queue_flush(self, now: float) -> None:
        if self._pending_exit in _LOCKOUT_EXITS:
            return
        if self.hold == Hold.DECEL:
            self._pending_exit = "flush"
            return
        if self.hold != Hold.HOLD:
            return
        self._leave_hold()
        self._flush_motion(now)
        if self.build.flush_reads_every_data_port:
            self.discard_rx()  # edge-preview `_start_queue_flush`: xio_flush_device(DEV_IS_DATA)
        self._abort_probe()  # cycle_feedhold.cpp `_run_queue_flush`
        self._set_state(MachineState.PROGRAM_STOP)

    def _job_kill(self, now: float) -> None:
        """A ^D read: `_start_job_kill` (edge-preview cycle_feedhold.cpp:559-581).

        Nothing in a lockout (case 0). In a moving cycle a hold first, the kill
        pending until it stands (2a, 2b); a ^D read meanwhile, on either port, finds
        the kill pending and adds nothing: `cm_request_job_kill` only sets a flag
        (:523) and the one `_run_job_kill` prints one `er` 207 (:551-553). The
        caller flushes the port's input whatever happens here (controller.cpp:282).
        """
        if self.state.is_lockout or self._pending_exit in _LOCKOUT_EXITS:
            return
        if self.hold == Hold.DECEL:
            self._pending_exit = "kill"
            return
        if self.hold == Hold.OFF and self._moving and self.state == MachineState.RUN:
            self._feedhold(now)
            self._pending_exit = "kill"
            return
        if self.hold == Hold.HOLD:
            self._leave_hold()
        self._flush_motion(now)  # `_run_queue_flush`: the planner, not the serial input
        self._abort_probe()
        self.interp.program_end()
        self._exception(Status.KILL_JOB, "Job killed by ^d")
        self._set_state(MachineState.PROGRAM_END)
        self._sr_now = True  # reported even when the board already was at program end

    def _flush_motion(self, now: float) -> None:
        """Empty the planner; the model continues from where the tool stands."""
        if self.active is not None:
            self.position = self.active.position(now)
            self.active = None
        self._qo += len(self.planner)
        self.planner.clear()
        self.interp.sync(self.position)
        self._sr_requested = True

    def _halt(self, now: float) -> None:
        """Stop the active block where the tool is; what is left of it stays queued."""
        active = self.active
        if active is None:
            return
        self.active = None
        self.position = active.position(now)
        rest = active.rest(now)
        self.planner.popleft()
        if rest is not None:
            self.planner.appendleft(rest)
        self._sr_requested = True

    # --- ALARM, SHUTDOWN, PANIC [10, seed 000]

    def _rejection(self) -> Status | None:
        return _REJECTED_BY.get(self.state)

    def _lockout(
        self, state: MachineState, status: Status, detail: str, *, unhome: bool = False
    ) -> None:
        """cm_alarm / cm_shutdown / cm_panic, as the board's build runs them (g2builds.py)."""
        if self.state == MachineState.PANIC:
            return
        if self.state == state or (state == MachineState.ALARM and self.state.is_lockout):
            return  # no alarm while already in an alarm state
        build = self.build
        if state == MachineState.PANIC or build.kill_alarms:
            self._lock_now(state, status, detail, unhome=unhome)
            return
        # 101.02+: a feedhold is requested whose exit action makes the lockout; the
        # exception report goes out now (alarm.cpp cm_alarm, cm_shutdown).
        if unhome:
            self.homed = dict.fromkeys(AXES, False)
        log.info("sim board lockout requested", state=state.name, status=int(status))
        self._exception(status, detail)
        self._sr_requested = True
        exit_ = "alarm" if state == MachineState.ALARM else "shutdown"
        if not build.alarm_holds_first:
            # 101.03: honoured only in a cycle that moves, and `_run_alarm` does nothing.
            if self.hold == Hold.OFF and self.state == MachineState.RUN:
                self._feedhold(self._clock())
            return
        if self.hold != Hold.OFF:
            return  # edge-preview cm_request_feedhold: ignored unless the hold is off
        now = self._clock()
        if self.state == MachineState.RUN and self.active is not None:
            self._feedhold(now)
            self._pending_exit = exit_
            return
        if self.state == MachineState.RUN:
            self._set_state(MachineState.HOLD)
        self._enter_hold(now, at=now)  # at rest the hold is in place at once...
        self._pending_exit = exit_  # ...and its exit action runs on the next pass (_advance)

    def _alarm_held(self, now: float, exit_: str) -> None:
        """edge-preview `_run_alarm`/`_run_shutdown` once held: the job is killed (with its
        own `er` 207), then the machine is in ALARM or SHUTDOWN (cycle_feedhold.cpp:354)."""
        if self.hold == Hold.HOLD:
            self._leave_hold()
        self._flush_motion(now)
        self._abort_probe()
        self.interp.program_end()
        self._exception(Status.KILL_JOB, "Job killed by ^d")
        self._pending_exit = None
        self._set_state(MachineState.ALARM if exit_ == "alarm" else MachineState.SHUTDOWN)
        self._sr_now = True

    def _lock_now(
        self, state: MachineState, status: Status, detail: str, *, unhome: bool = False
    ) -> None:
        """The lockout at once: PANIC on every build, ALARM and SHUTDOWN before 101.02."""
        self._flush_motion(self._clock())
        self.hold = Hold.OFF
        self._pending_exit = None
        self._hold_point = None
        self._p2 = None
        if unhome:
            self.homed = dict.fromkeys(AXES, False)
        log.info("sim board lockout", state=state.name, status=int(status), detail=detail)
        self._exception(status, detail)
        if state == MachineState.PANIC:
            # cm_panic() requests no status report (alarm.cpp); one asked for shows it.
            self.state = state
            return
        self._abort_probe()  # cm_probing_cycle_callback, seeing ALARM or SHUTDOWN
        self._set_state(state)

    def _clear(self) -> None:
        """ALARM -> PROGRAM_STOP, SHUTDOWN -> PROGRAM_END; PANIC stays [10]."""
        if self.state == MachineState.ALARM:
            self._set_state(MachineState.PROGRAM_STOP)
            if self.build.kill_alarms:
                self._flush_to_command()  # 100.26 canonical_machine.cpp:886
        elif self.state == MachineState.SHUTDOWN:
            self._set_state(MachineState.PROGRAM_END)

    def _parse_clear(self) -> None:
        """A block that is exactly M2/M30 clears ALARM, and (per the code) SHUTDOWN [10]."""
        if self.state in (MachineState.ALARM, MachineState.SHUTDOWN):
            self._clear()

    # --- the end of a G38.2-G38.5 probing cycle (cycle_probing.cpp; its start: planner.py)

    def _probe_finish(self) -> None:
        """`_probing_finish`: keep where the tool is, alarm if it never tripped, report."""
        cycle = self._probing
        if cycle is None:
            return
        self._probing = None
        self.interp.motion = None  # _probe_restore_settings: G80
        self.interp.sync(self.position)
        if not cycle.tripped and cycle.alarm:
            self._lockout(MachineState.ALARM, Status.PROBE_CYCLE_FAILED, "probing failed")
        self._sr_requested = True
        # `_send_probe_report` (when `prbr`, on by default): sprintf'd, %0.5f per axis.
        values = ",".join(f'"{a}":{self.position.get(a, 0.0):0.5f}' for a in PROBE_AXES)
        self._emit_line(f'{{"prb":{{"e":{1 if cycle.tripped else 0},{values}}}}}')

    def _abort_probe(self) -> None:
        """`cm_abort_probing`: a lockout or a flush ended the cycle; reported, no alarm."""
        if self._probing is not None:
            self._probing.tripped = self._probing.alarm = False
            self._probe_finish()
