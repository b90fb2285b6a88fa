"""The simulated g2core: settings, machine state, planner, and every answer it gives.

This is the firmware's main loop without the hardware: the controller feeds
it scanned input (controls at once, data lines into per-port RX queues) and
calls `tick()` until it reports no progress, then sleeps until
`next_deadline()` or new input. Output leaves as text lines through `emit`.
No I/O and no asyncio here; the clock is injected.

Which g2core behaviour each part follows is cited from ../shared/spec/g2core.md
(sections in brackets).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

import structlog

from hostd.protocol.states import MachineState
from hostd.protocol.status import Status, message
from hostd.sim import gcode, relaxed, reports
from hostd.sim.config import AXES, EPS, SimConfig
from hostd.sim.gcode import (
    Block,
    Dwell,
    Home,
    Interpreter,
    Move,
    Probe,
    ProgramEnd,
    SetPosition,
)
from hostd.sim.motion import Active, start_block
from hostd.sim.output import CYCLES, OUTPUT_BUFFER_LEN, Hold, Output
from hostd.sim.probing import (
    MINIMUM_PROBE_TRAVEL,
    PROBE_AXES,
    ProbeCycle,
    probe_touching,
    probe_trip,
)
from hostd.sim.scanner import DataLine
from hostd.sim.settings import Settings

log = structlog.get_logger(__name__)

ENQ, JOB_KILL, RESET = 0x05, 0x04, 0x18
RX_REPORT = 254  # `{rx:n}` is a constant on ARM [7.1]
INPUTS = {"x": 1, "y": 3, "z": 5}  # limit switch input numbers, for `er` details
ESTOP_INPUT, PANIC_INPUT = 7, 9
# planner.h BLOCK_TIMEOUT_MS: from rest, the planner takes blocks in before it moves
# (PLANNER_STARTUP, planner.cpp mp_planner_callback) until it is full or none has come
# for this long (real seconds; divided by speed_factor as moves are).
BLOCK_TIMEOUT = 0.030

_REJECTED_BY = {
    MachineState.ALARM: Status.COMMAND_REJECTED_BY_ALARM,
    MachineState.SHUTDOWN: Status.COMMAND_REJECTED_BY_SHUTDOWN,
    MachineState.PANIC: Status.COMMAND_REJECTED_BY_PANIC,
}
# What cm_alarm / cm_shutdown / cm_panic each leave the machine in (alarm.cpp).
_LOCKOUT_PATHS = {
    "alarm": MachineState.ALARM,
    "shutdown": MachineState.SHUTDOWN,
    "panic": MachineState.PANIC,
}


class Board(Output):
    """One g2core board; see the module docstring for how it is driven."""

    def __init__(
        self,
        config: SimConfig,
        *,
        emit: Callable[[str], None],
        clock: Callable[[], float],
        reset: Callable[[], None],
    ) -> None:
        self.config = config
        self._emit_line = emit
        self._clock = clock
        self._request_reset = reset
        self.rx = {}
        self._rx_bytes = {}
        self.output_blocked = False  # the host stopped reading; the main loop stalls
        self.ack_delay = 0.0
        # Input pins are wired to the machine, not kept by the firmware: a reset keeps them.
        self.inputs = dict.fromkeys(reports.INPUT_KEYS, 0)
        # So is the rest of the machine a test sets up: a reset keeps these too.
        self.probe_surface = None  # axis, machine mm the probe touches
        self.homing_failure = None  # axis, why homing it fails
        self.output_buffer = OUTPUT_BUFFER_LEN  # answers this long or longer are not printed
        self.overflow_reported = True  # as an `er` 113, or (False) not at all
        self.glitches = {}  # status values computed wrong (nan, inf), by key
        self.power_on()

    # --- power and connection

    def power_on(self) -> None:
        """The state after a reset: READY, unhomed, nothing queued, default settings."""
        self.settings = Settings(self.config)
        self.state = MachineState.READY
        self.interp = Interpreter()
        self.planner = deque()
        self._last_block_at = 0.0  # when the last block went into the planner
        self._planner_running = False  # PLANNER_IDLE/STARTUP (False) or moving blocks (True)
        self.active: Active | None = None
        self.position = dict.fromkeys(AXES, 0.0)
        self.homed = dict.fromkeys(AXES, False)
        self.hold = Hold.OFF
        self._pending_exit = None  # what to do once a hold has stopped
        self._hold_point = None
        self._p2 = None  # the in-hold (secondary) planner's model
        self.interlock_input = False
        self.interlocked = False
        self._ack = None
        self._sr_last = {}
        self._sr_requested = False
        self._sr_now = False
        self._sr_next = 0.0
        self._qr_last = None
        self._qi = self._qo = 0
        self._probing = None
        self._init_message_due = False
        for port in self.rx:
            self.discard_rx(port)

    def connected(self) -> None:
        """A host opened the board: per-open settings back to their defaults [10]."""
        self.settings.reset_per_open()
        self._sr_last = {}
        self._qr_last = None

    def disconnected(self) -> None:
        """The last host closed the board."""
        self.settings.reset_per_open()

    # --- input: the controller feeds scanned events here

    def percent_is_control(self) -> bool:
        """`%` is a queue flush only while there is a hold (cm_has_hold) [8]."""
        return self.hold != Hold.OFF

    def open_rx(self, port: str) -> None:
        self.rx[port] = deque()
        self._rx_bytes[port] = 0

    def close_rx(self, port: str) -> None:
        self.rx.pop(port, None)
        self._rx_bytes.pop(port, None)

    def rx_bytes(self, port: str) -> int:
        """Bytes of data lines waiting in `port`'s RX buffer."""
        return self._rx_bytes.get(port, 0)

    def queue_line(self, port: str, line: DataLine) -> None:
        queue = self.rx.get(port)
        if queue is not None:
            queue.append(line)
            self._rx_bytes[port] += line.size

    def discard_rx(self, port: str | None = None) -> None:
        """Drop data lines not yet read: they never get a response [7.1]."""
        for name in [port] if port is not None else list(self.rx):
            if name in self.rx:
                self.rx[name].clear()
                self._rx_bytes[name] = 0

    def realtime(self, port: str, char: int) -> None:
        """A single-character control [8]."""
        now = self._clock()
        if char == ord("!"):
            self._feedhold(now)
        elif char == ord("~"):
            self._cycle_start()
        elif char == ord("%"):
            self.discard_rx(port)  # everything before the % on its port is skipped
            self._queue_flush(now)
        elif char == JOB_KILL:
            self._job_kill(now)
        elif char == ENQ:
            self._emit({"ack": True})
        elif char == RESET:
            self._request_reset()
        self._flush_sr()

    def control(self, text: bytes, linelen: int) -> None:
        """A `{...}` control line, run ahead of queued data lines [7.1]."""
        self._json(text.decode("latin-1"), linelen, data=False)
        self._flush_sr()

    # --- injections (hardware inputs)

    def limit_switch(self, axis: str) -> None:
        if self.settings["lim"]:
            detail = f"input {INPUTS.get(axis, 1)}"
            self._lockout(MachineState.ALARM, Status.LIMIT_SWITCH_HIT, detail, unhome=True)
        self._flush_sr()

    def estop(self, active: bool) -> None:
        if active:
            detail = f"input {ESTOP_INPUT}"
            self._lockout(MachineState.SHUTDOWN, Status.SHUTDOWN, detail, unhome=True)
        self._flush_sr()

    def panic(self) -> None:
        self._lockout(MachineState.PANIC, Status.PANIC, f"input {PANIC_INPUT}")
        self._flush_sr()

    def firmware_exception(self, status: int, path: str, detail: str) -> None:
        """One call of cm_alarm / cm_shutdown / cm_panic (see callsites.py)."""
        state = _LOCKOUT_PATHS[path]
        self._lockout(state, Status(status), detail, unhome=state == MachineState.SHUTDOWN)
        self._flush_sr()

    def glitch(self, key: str, value: float | None) -> None:
        """Status key `key` reads `value` (nan, inf) until glitched back to None."""
        if value is None:
            self.glitches.pop(key, None)
        else:
            self.glitches[key] = value
        if key in self.settings.sr_keys:
            self._sr_now = True
        self._flush_sr()

    def interlock(self, active: bool) -> None:
        """Safety interlock input: a halt ending in state 11, no exception report [5]."""
        self.interlock_input = active
        now = self._clock()
        if active and self.settings["saf"] and not self.interlocked:
            self.interlocked = True
            if self.state.is_lockout:
                pass  # the lockout has stopped everything already
            elif self.active is not None and self.active.decelerating:
                self._enter_hold(now, at=now)  # a halt cuts the deceleration short
                if self.hold == Hold.HOLD:
                    self._set_state(MachineState.INTERLOCK)
            elif self.active is not None:
                self._halt(now)
                self._set_state(MachineState.INTERLOCK)
            elif self.hold == Hold.HOLD:
                self._set_state(MachineState.INTERLOCK)
        elif not active and self.interlocked:
            self.interlocked = False
            if self.state == MachineState.INTERLOCK:
                if self.hold != Hold.OFF:
                    self._set_state(MachineState.HOLD)
                elif self.planner:
                    self._set_state(MachineState.RUN)
                else:
                    self._set_state(MachineState.PROGRAM_STOP)
        self._flush_sr()

    def set_input(self, key: str, value: float | int) -> None:
        """A digital or analogue input changed: reported at once if it is in the list [4]."""
        value = reports.number(value, reports.places(key))  # a change too small to print is none
        if self.inputs[key] == value:
            return
        self.inputs[key] = value
        if key in self.settings.sr_keys:
            self._sr_now = True
        self._flush_sr()

    def set_homed(self, homed: bool) -> None:
        self.homed = dict.fromkeys(AXES, homed)
        self._sr_requested = True

    # --- the main loop

    def tick(self) -> bool:
        """Do one thing that is due; False when nothing is."""
        now = self._clock()
        progressed = self._step(now)
        self._flush_sr()
        return progressed

    def next_deadline(self) -> float | None:
        """When `tick` has something to do next without new input (None: not until input)."""
        times: list[float] = []
        if self.active is not None:
            times.append(self.active.end)
        elif self._priming():
            times.append(self._last_block_at + self._block_timeout)
        if not self.output_blocked:
            if self._ack is not None:
                times.append(self._ack[0])
            if self._sr_requested or self._moving:
                times.append(self._sr_next)
        return min(times) if times else None

    def _step(self, now: float) -> bool:
        if self._ack is not None and not self.output_blocked and now >= self._ack[0]:
            self._emit(self._ack[1])
            self._ack = None
            return True
        return self._advance(now) or self._dispatch() or self._timed_reports(now)

    def _advance(self, now: float) -> bool:
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
        self.active = start_block(
            block,
            self.position,
            now,
            speed_factor=cfg.speed_factor,
            rapid_rate=cfg.rapid_rate,
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

    # --- G38.2-G38.5 probing (cycle_probing.cpp)

    def _probe_start(self, block: Probe) -> Probe | None:
        """`_probing_start`: check the travel and the input, then move until it trips."""
        cycle = self._probing = ProbeCycle(alarm=block.alarm)
        target = block.move.target
        travel = math.dist([self.position[a] for a in AXES], [target[a] for a in AXES])
        if travel < MINIMUM_PROBE_TRAVEL:
            self._probe_exception(Status.PROBE_TRAVEL_TOO_SMALL)
            return None
        if probe_touching(self.probe_surface, self.position) == block.on_contact:
            self._probe_exception(Status.PROBE_IS_ALREADY_TRIPPED)
            return None
        trip = probe_trip(self.probe_surface, self.position, block)
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

    # --- data lines: read in order, only when the planner has room [7.1]

    def _dispatchable(self) -> bool:
        if self._ack is not None or self.output_blocked:
            return False
        if self._probing is not None or any(isinstance(b, Probe) for b in self.planner):
            return False  # cm_probing_cycle_callback: nothing is read until the cycle ends
        if not self.state.is_lockout and len(self.planner) >= self.config.planner_depth:
            return False  # in a lockout lines are drained and rejected regardless [10]
        return any(self.rx.values())

    def _dispatch(self) -> bool:
        if not self._dispatchable():
            return False
        for port, queue in self.rx.items():
            if queue:
                line = queue.popleft()
                self._rx_bytes[port] -= line.size
                self._data_line(line.text.decode("latin-1"))
                return True
        return False

    def _data_line(self, text: str) -> None:
        linelen = len(text)
        stripped = text.lstrip(" \t")
        first = stripped[:1]
        if first == "%":
            return  # swallowed by the single-character branch, no response [2.2]
        if first and first in "!~\x04\x05\x18":
            self.realtime("", ord(first))
            return
        if first == "{":
            self._json(stripped, linelen, data=True)
        elif first == "?":
            self._respond({"sr": self._sr_full()}, Status.OK, linelen, data=True)
        elif first == "$":
            self._text(stripped, linelen)
        else:
            status, n = self._gcode(text)
            body: dict[str, Any] = {"gc": text} if self._jv >= 5 else {}
            self._respond(body, status, linelen, data=True, n=n)
            self._sr_requested = True

    # --- JSON and text commands

    def _json(self, text: str, linelen: int, *, data: bool) -> None:
        try:
            pairs = relaxed.parse(text)
        except relaxed.RelaxedJsonError:
            body: dict[str, Any] = {"err": text} if self._jv >= 2 else {}
            self._respond(body, Status.JSON_SYNTAX_ERROR, linelen, data=data)
            return
        body = {}
        status, n = Status.OK, 0
        for key, value in pairs.items():
            status, line = self._pair(key, value, body)
            n = n or line
            if status != Status.OK:
                break
        self._respond(body, status, linelen, data=data, n=n)
        self._sr_requested = True

    def _text(self, text: str, linelen: int) -> None:
        """`$key`, `$key=value`, `$clear`: text-mode commands, answered in JSON [11]."""
        command = relaxed.normalize(text[1:])
        body: dict[str, Any] = {}
        if command in ("", "$"):
            body["sys"] = self.settings.system_group()
            self._respond(body, Status.OK, linelen, data=True)
            return
        key, eq, raw = command.partition("=")
        value = _text_value(raw) if eq else None
        status, n = self._pair(key, value, body)
        self._respond(body, status, linelen, data=True, n=n)
        self._sr_requested = True

    def _pair(self, key: str, value: relaxed.Value, body: dict[str, Any]) -> tuple[Status, int]:
        """One name/value pair: a GET (value None) or a SET; returns status and N word."""
        if value is None:
            return self._get(key, body), 0
        if isinstance(value, str) and gcode.is_program_end(value):
            self._parse_clear()
        rejected = self._rejection()
        if rejected is not None:  # SETs are actions: drained and rejected [10]
            body[key] = _echo(value)
            return rejected, 0
        if key in ("gc", "gc2"):
            if not isinstance(value, str):
                body[key] = _echo(value)
                return Status.VALUE_TYPE_ERROR, 0
            if self._jv >= 5:
                body[key] = value
            return self._gcode(value, in_hold=key == "gc2")
        if key == "sr":
            return self._set_sr(value, body), 0
        return self._set(key, value, body), 0

    def _get(self, key: str, body: dict[str, Any]) -> Status:
        body[key] = None
        if key == "sr":
            body[key] = self._sr_full()
        elif key in ("clear", "clr"):
            self._clear()
        elif key == "alarm":
            self._lockout(MachineState.ALARM, Status.ALARM, "sent by host")
        elif key == "shutd":
            self._lockout(MachineState.SHUTDOWN, Status.SHUTDOWN, "sent by host", unhome=True)
        elif key == "panic":
            self._lockout(MachineState.PANIC, Status.PANIC, "sent by host")
        elif key == "er":
            self._exception(Status.GENERIC_EXCEPTION_REPORT, "bogus exception report")
        elif key == "sys":
            body[key] = self.settings.system_group()
        elif key == "qr":
            body[key] = self._free
        elif key in ("qi", "qo"):
            body[key] = self._qi if key == "qi" else self._qo
            setattr(self, f"_{key}", 0)
        elif key == "rx":
            body[key] = RX_REPORT
        elif key in self.settings:
            body[key] = self.settings.get(key)
        elif key in reports.SR_KEYS:
            body[key] = self._values(self._clock())[key]
        else:
            return Status.UNRECOGNIZED_NAME
        return Status.OK

    def _set(self, key: str, value: relaxed.Value, body: dict[str, Any]) -> Status:
        body[key] = _echo(value)
        if key in ("clear", "clr", "alarm", "shutd", "panic"):
            return self._get(key, body)  # functions run the same either way
        if key in reports.SR_KEYS:
            return Status.PARAMETER_IS_READ_ONLY
        if key == "defa":
            return self._defaults(value, body)
        if key not in self.settings:
            return Status.UNRECOGNIZED_NAME
        status = self.settings.set(key, value)
        if status == Status.OK:
            body[key] = self.settings.get(key)
        return status

    def _defaults(self, value: relaxed.Value, body: dict[str, Any]) -> Status:
        """config.cpp `set_defaults`: every setting back to the profile's default.

        `_set_defa` prints its startup message ("Initializing configs...", status
        15) before the line's answer, and the answer is `{"defa":true}` [11].
        """
        if not value:
            return Status.OK  # help_defa: a help screen (text), which hostd never asks for
        self.settings = Settings(self.config)
        self._sr_last = {}
        self._init_message_due = True
        body["defa"] = True
        return Status.OK

    def _set_sr(self, value: relaxed.Value, body: dict[str, Any]) -> Status:
        """`{sr:{...}}` replaces the report list; the answer is a full report [4]."""
        body["sr"] = _echo(value)
        status = self.settings.set_status_report(value)
        if status == Status.OK:
            self._sr_last = {}
            body["sr"] = self._sr_full()
        return status

    # --- G-code

    def _gcode(self, text: str, *, in_hold: bool = False) -> tuple[Status, int]:
        if gcode.is_program_end(text):
            self._parse_clear()
        rejected = self._rejection()
        if rejected is not None:
            return rejected, 0
        if in_hold and self.hold == Hold.HOLD:
            return self._gcode_in_hold(text)
        outcome = self.interp.execute(text, self._soft_limits)
        self._soft_limit_alarm(outcome.status)
        if outcome.alarm:  # cm_straight_probe refused it with cm_alarm()
            self._lockout(MachineState.ALARM, outcome.status, outcome.alarm)
        for block in outcome.blocks:
            self.planner.append(block)
            self._qi += 1
            self._last_block_at = self._clock()
            if isinstance(block, Move | Dwell) and self._at_rest_for_a_cycle():
                self._set_state(MachineState.RUN)  # cm_cycle_start, as the move is parsed
        return outcome.status, outcome.n

    def _gcode_in_hold(self, text: str) -> tuple[Status, int]:
        """`{gc2:...}` in a hold: the secondary planner runs it at once [8, seed 002]."""
        if self._p2 is None:
            self._p2 = self.interp.copy()
            self._p2.sync(self.position)
        outcome = self._p2.execute(text, self._soft_limits)
        self._soft_limit_alarm(outcome.status)
        for block in outcome.blocks:
            if isinstance(block, Move):
                self.position = dict(block.target)
            elif isinstance(block, Home):
                for axis in block.axes:
                    self.position[axis] = 0.0
                    self.homed[axis] = True
            elif isinstance(block, SetPosition):
                self.position.update(block.values)
                for axis in block.values:
                    self.homed[axis] = True
            self._sr_requested = True
        return outcome.status, outcome.n

    def _soft_limits(self, target: Mapping[str, float]) -> Status:
        """Soft limits apply to homed axes while `sl` is on [10, seed 000]."""
        if not self.settings["sl"]:
            return Status.OK
        for i, axis in enumerate(AXES):
            if not self.homed[axis]:
                continue
            if target[axis] < self.settings[f"{axis}tn"] - EPS:
                return Status(Status.SOFT_LIMIT_EXCEEDED_XMIN + 2 * i)
            if target[axis] > self.settings[f"{axis}tm"] + EPS:
                return Status(Status.SOFT_LIMIT_EXCEEDED_XMAX + 2 * i)
        return Status.OK

    def _soft_limit_alarm(self, status: Status) -> None:
        if Status.SOFT_LIMIT_EXCEEDED <= status <= Status.SOFT_LIMIT_EXCEEDED_ARC:
            self._lockout(MachineState.ALARM, status, "soft_limits")

    # --- feedhold, resume, flush, kill [8, seed 002]

    def _feedhold(self, now: float) -> None:
        active = self.active
        if self.hold != Hold.OFF or self.state != MachineState.RUN:
            return  # ignored unless in a cycle
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

    def _leave_hold(self) -> None:
        if self._hold_point is not None:
            self.position = self._hold_point  # the return move to the hold point
        self.hold = Hold.OFF
        self._hold_point = None
        self._p2 = None

    def _cycle_start(self) -> None:
        if self.hold == Hold.DECEL:
            self._pending_exit = "resume"
            return
        if self.hold != Hold.HOLD or self.interlocked:
            return
        self._leave_hold()
        self._set_state(MachineState.RUN if self.planner else MachineState.PROGRAM_STOP)

    def _queue_flush(self, now: float) -> None:
        if self.hold == Hold.DECEL:
            self._pending_exit = "flush"
            return
        if self.hold != Hold.HOLD:
            return
        self._leave_hold()
        self._flush_motion(now)
        self.discard_rx()
        self._abort_probe()  # cycle_feedhold.cpp `_run_queue_flush`
        self._set_state(MachineState.PROGRAM_STOP)

    def _job_kill(self, now: float) -> None:
        if self.state.is_lockout:
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
        self._flush_motion(now)
        self.discard_rx()
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
        if self.state == MachineState.PANIC:
            return
        if self.state == state or (state == MachineState.ALARM and self.state.is_lockout):
            return  # no alarm while already in an alarm state
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
        elif self.state == MachineState.SHUTDOWN:
            self._set_state(MachineState.PROGRAM_END)

    def _parse_clear(self) -> None:
        """A block that is exactly M2/M30 clears ALARM, and (per the code) SHUTDOWN [10]."""
        if self.state in (MachineState.ALARM, MachineState.SHUTDOWN):
            self._clear()


def _echo(value: relaxed.Value) -> Any:
    if isinstance(value, float):
        return reports.number(value, 5)
    if isinstance(value, dict):
        return {k: _echo(v) for k, v in value.items()}
    return value


def _text_value(raw: str) -> relaxed.Value:
    """The value of `$key=value`: a number, t/f, or the text itself."""
    if not raw or raw.startswith("n"):
        return None
    try:
        return float(raw)
    except ValueError:
        pass
    if raw in ("t", "true", "f", "false"):
        return raw.startswith("t")
    return raw
