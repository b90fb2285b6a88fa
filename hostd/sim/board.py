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

from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

from hostd.protocol.states import MachineState
from hostd.protocol.status import Status
from hostd.sim import gcode, relaxed, reports
from hostd.sim.config import AXES, EPS, SimConfig
from hostd.sim.gcode import Dwell, Home, Interpreter, Move, SetPosition
from hostd.sim.motion import Active
from hostd.sim.output import OUTPUT_BUFFER_LEN, Hold
from hostd.sim.planner import BLOCK_TIMEOUT, Planner
from hostd.sim.scanner import DataLine
from hostd.sim.settings import Settings

__all__ = ["BLOCK_TIMEOUT", "Board"]  # BLOCK_TIMEOUT lives in planner.py

RX_REPORT = 254  # `{rx:n}` is a constant on ARM [7.1]
INPUTS = {"x": 1, "y": 3, "z": 5}  # limit switch input numbers, for `er` details
ESTOP_INPUT, PANIC_INPUT = 7, 9
# What cm_alarm / cm_shutdown / cm_panic each leave the machine in (alarm.cpp).
_LOCKOUT_PATHS = {
    "alarm": MachineState.ALARM,
    "shutdown": MachineState.SHUTDOWN,
    "panic": MachineState.PANIC,
}


class Board(Planner):
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

    # --- data lines: read in order, only when the planner has room [7.1]

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
