"""The simulated g2core's planner: blocks from the queue into motion.

The layer of `Board` (board.py) above its stops (stops.py): the main loop's
advance through the planner, with its start-up wait (planner.cpp
PLANNER_STARTUP, BLOCK_TIMEOUT_MS), homing that fails, and the start of the
G38.x probing cycle. What stops the motion (holds, flush, kill, lockouts)
and the probing cycle's end are in stops.py; which data line is read next is
in intake.py.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

from hostd.protocol.states import MachineState
from hostd.protocol.status import Status, message
from hostd.sim.config import AXES
from hostd.sim.gcode import Block, Dwell, Home, Move, Probe, ProgramEnd, SetPosition
from hostd.sim.motion import Active, Traversed, start_block
from hostd.sim.output import CYCLES, Hold
from hostd.sim.probing import MINIMUM_PROBE_TRAVEL, ProbeCycle, contact
from hostd.sim.stops import _LOCKOUT_EXITS, Stops

# planner.h BLOCK_TIMEOUT_MS: from rest, the planner takes blocks in before it moves
# (PLANNER_STARTUP, planner.cpp mp_planner_callback) until it is full or none has come
# for this long (real seconds; divided by speed_factor as moves are).
BLOCK_TIMEOUT = 0.030


class Planner(Stops):
    """Blocks from the planner into motion; the holds and lockouts are below (stops.py)."""

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
