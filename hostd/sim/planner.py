"""The simulated g2core's planner and motion, and everything that stops them.

The layer of `Board` (board.py) above its output (output.py): the main
loop's advance through the planner, with its start-up wait (planner.cpp
PLANNER_STARTUP, BLOCK_TIMEOUT_MS), homing that fails, the G38.x probing
cycle, the realtime controls, feedhold, resume, queue flush and job kill
[8], and the lockouts ALARM, SHUTDOWN and PANIC [10].
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import structlog

from hostd.protocol.states import MachineState
from hostd.protocol.status import Status, message
from hostd.sim.config import AXES
from hostd.sim.gcode import Block, Dwell, Home, Move, Probe, ProgramEnd, SetPosition
from hostd.sim.motion import Active, Traversed, start_block
from hostd.sim.output import CYCLES, Hold, Output
from hostd.sim.probing import (
    MINIMUM_PROBE_TRAVEL,
    PROBE_AXES,
    ProbeCycle,
    contact,
)

log = structlog.get_logger(__name__)

ENQ, JOB_KILL, RESET = 0x05, 0x04, 0x18
_LOCKOUT_EXITS = ("alarm", "shutdown")  # a hold's exit that makes a lockout (101.05+)
# planner.h BLOCK_TIMEOUT_MS: from rest, the planner takes blocks in before it moves
# (PLANNER_STARTUP, planner.cpp mp_planner_callback) until it is full or none has come
# for this long (real seconds; divided by speed_factor as moves are).
BLOCK_TIMEOUT = 0.030

_REJECTED_BY = {
    MachineState.ALARM: Status.COMMAND_REJECTED_BY_ALARM,
    MachineState.SHUTDOWN: Status.COMMAND_REJECTED_BY_SHUTDOWN,
    MachineState.PANIC: Status.COMMAND_REJECTED_BY_PANIC,
}


class Planner(Output):
    """Blocks from the planner into motion, and the holds and lockouts that stop it."""

    # --- the main loop's advance: run what the planner holds

    def _advance(self, now: float) -> bool:
        if self.hold == Hold.HOLD and self._pending_exit in _LOCKOUT_EXITS:
            # cm_operation_runner_callback runs the alarm's exit action once held.
            self._alarm_held(now, self._pending_exit)
            return True
        active = self.active
        if active is not None:
            if now < active.end:
                return False
            if active.decelerating:
                self._hold_reached(now)
            else:
                self._finish(active)
            return True
        if self.hold != Hold.OFF or self.state.is_lockout:
            return False
        if self.planner:
            if self.interlocked:
                if self.state == MachineState.INTERLOCK:
                    return False
                self._set_state(MachineState.INTERLOCK)
                return True
            if self._priming() and now < self._last_block_at + self._block_timeout:
                return False
            self._start(now)
            return True
        if self.state in CYCLES and not self._dispatchable():
            self._set_state(MachineState.PROGRAM_STOP)
            return True
        return False

    @property
    def _block_timeout(self) -> float:
        return BLOCK_TIMEOUT / self.config.speed_factor

    def _priming(self) -> bool:
        """PLANNER_STARTUP: from rest, a move waits for a full planner or BLOCK_TIMEOUT.

        g2core plans before it moves: the first move of a job starts once the
        planner is full or no block has come for 30 ms, so a host sending a
        job's lines does not starve it at the start. The state is already RUN:
        the move's parsing started the cycle (cm_cycle_start in cm_straight_feed).
        """
        return (
            not self._planner_running
            and bool(self.planner)
            and isinstance(self.planner[0], Move | Dwell)
            and len(self.planner) < self.config.planner_depth
        )

    def _start(self, now: float) -> None:
        self._planner_running = True
        block = self.planner[0]
        if isinstance(block, ProgramEnd):
            self._pop()
            self.settings.reset_overrides()  # _exec_program_finalize: cm_reset_overrides
            self._set_state(MachineState.PROGRAM_END)
            return
        if isinstance(block, SetPosition):
            self._pop()
            self.position.update(block.values)
            for axis in block.values:
                self.homed[axis] = True
            self._sr_requested = True
            return
        if isinstance(block, Home) and self._homing_fails(block):
            return
        if isinstance(block, Probe):
            started = self._probe_start(block)
            if started is None:
                return
            block = started
        cfg = self.config
        if isinstance(block, Move | Probe):
            move = block if isinstance(block, Move) else block.move
            self.traversed.append(Traversed(dict(self.position), move))
        if isinstance(block, Move) and not block.rapid:
            # The feed override scales the feed moves planned after it (plan_zoid.cpp:148).
            block = replace(block, feed=block.feed * self.settings.override("feed"))
        self.active = start_block(
            block,
            self.position,
            now,
            speed_factor=cfg.speed_factor,
            rapid_rate=cfg.rapid_rate * self.settings.override("rapid"),
            instant=cfg.instant,
        )
        if isinstance(block, Home):
            self._set_state(MachineState.HOMING)
        elif isinstance(block, Probe):
            self._set_state(MachineState.PROBE)
        else:
            self._set_state(MachineState.RUN)

    def _homing_fails(self, block: Home) -> bool:
        """cycle_homing.cpp `_homing_error_exit`: the cycle starts and ends at once.

        It prints `{"r":{"msg":"X axis <why>"},"f":[1,240,1]}`, an `{r}` that
        answers no line (the count is cs.linelen + 1, reset by the last answer),
        restores the G-code model and leaves the axis not homed. No alarm: the
        lines after it run.
        """
        failure = self.homing_failure
        if failure is None or failure[0] not in block.axes:
            return False
        axis, why = failure
        self._pop()
        self._set_state(MachineState.HOMING)
        self._flush_sr()
        body: dict[str, Any] = {}
        if self._jv >= 2:  # nv_add_conditional_message: only from JV_MESSAGES
            body["msg"] = f"{axis.upper()} axis {message(why)}"
        if self._jv:  # json_print_response: nothing only when silent
            self._emit({"r": body, "f": [1, int(Status.HOMING_CYCLE_FAILED), 1]})
        self.interp.sync(self.position)  # the model's homing target was never reached
        self._set_state(MachineState.PROGRAM_STOP)
        return True

    def _finish(self, active: Active) -> None:
        self.active = None
        if active.move is not None:
            self.position = dict(active.move.target)
        block = self._pop()
        if isinstance(block, Home):
            for axis in block.axes:
                self.homed[axis] = True
        elif isinstance(block, Probe):
            self._probe_finish()
        self._sr_requested = True

    def _pop(self) -> Block:
        self._qo += 1
        return self.planner.popleft()

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

    # --- G38.2-G38.5 probing (cycle_probing.cpp)

    def _probe_start(self, block: Probe) -> Probe | None:
        """`_probing_start`: check the travel and the input, then move until it trips."""
        cycle = self._probing = ProbeCycle(alarm=block.alarm)
        target = block.move.target
        travel = math.dist([self.position[a] for a in AXES], [target[a] for a in AXES])
        if travel < MINIMUM_PROBE_TRAVEL:
            self._probe_exception(Status.PROBE_TRAVEL_TOO_SMALL)
            return None
        if self.probe_closed() == block.on_contact:  # gpio_read_input(pb.probe_input)
            self._probe_exception(Status.PROBE_IS_ALREADY_TRIPPED)
            return None
        trip = None
        if self.settings["prbin"]:  # input 0 is none: gpio_read_input(0) reads false
            trip = contact(
                self.probe_surface_here(),
                self.touch_plate,
                self.position,
                block.move.target,
                block.on_contact,
            )
        if trip is not None:  # the move ends where the input trips
            cycle.tripped = True
            block = Probe(Move(trip, block.move.feed, block.n), block.on_contact, block.alarm)
            self.planner[0] = block
        return block

    def _probe_exception(self, status: Status) -> None:
        """`_probing_exception_exit`: settings restored, then cm_alarm(status, "probe error")."""
        self._pop()
        self._probing = None
        self.interp.motion = None
        self.interp.sync(self.position)
        self._lockout(MachineState.ALARM, status, "probe error")

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

    # --- data lines: read in order, only when the planner has room [7.1]

    def _dispatchable(self) -> bool:
        if self._ack is not None or self.output_blocked:
            return False
        if self._probing is not None or any(isinstance(b, Probe) for b in self.planner):
            return False  # cm_probing_cycle_callback: nothing is read until the cycle ends
        if self.hold != Hold.OFF and not self.build.kill_alarms:
            return False  # cm_feedhold_command_blocker (101.03 cycle_feedhold.cpp:294)
        if not self.state.is_lockout and len(self.planner) >= self.config.planner_depth:
            return False  # in a lockout lines are drained and rejected regardless [10]
        return any(self.rx.values()) or any(self.rx_controls.values())

    def discard_rx(self, port: str | None = None, *, controls: bool = True) -> None:
        """Drop data lines not yet read: they never get a response [7.1]. A flush to the
        command (`controls=False`) keeps the controls that came after it."""
        for name in [port] if port is not None else list(self.rx):
            if name in self.rx:
                self._rx_out[name] += len(self.rx[name])
                self.rx[name].clear()
                self._rx_bytes[name] = 0
            if controls and name in self.rx_controls:
                self.rx_controls[name].clear()

    def _control_read(self, port: str, mark: int | None) -> None:
        """`readline` returned a control from `port`: a flush to the command now drops the
        data lines that came in before it (`mark`; None: every one queued so far)."""
        if port in self._control_last:
            self._control_last[port] = True
            self._flush_mark[port] = self._rx_in[port] if mark is None else mark

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

    def _flush_to_command(self) -> None:
        """`xio_flush_to_command`: every port whose last line read was a control drops the
        data lines that came in before that control (xio.cpp:984-1017, `flushToCommand`:
        the read pointer moves to where the scan stopped, just past the control, :1004);
        the lines behind it, and the other ports' lines, stay.

        On a two-port link a ^D on the control port flushes that port alone: the
        data port's lines are read and run after it, up to the data port's own ^D.
        """
        for port, last in self._control_last.items():
            if not last:
                continue
            self._control_last[port] = False
            queue, mark = self.rx[port], self._flush_mark[port]
            while queue and self._rx_out[port] < mark:
                self._rx_bytes[port] -= queue.popleft().size
                self._rx_out[port] += 1

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
