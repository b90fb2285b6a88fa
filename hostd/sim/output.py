"""What the simulated g2core prints, and the state every part of the board reads.

The bottom layer of `Board` (board.py): the board's state, declared once for
every layer, and all it prints. The `{r}` answer to every line
(json_print_response), exception reports (`er`), startup messages, status and
queue reports, and the JSON the firmware prints them in [2, 4, 6].
"""

from __future__ import annotations

import json
import math
from collections import deque
from collections.abc import Callable
from enum import IntEnum
from typing import Any

import structlog

from hostd.protocol.g2builds import Build
from hostd.protocol.states import MachineState
from hostd.protocol.status import Status, message
from hostd.sim import reports
from hostd.sim.config import AXES, SimConfig
from hostd.sim.gcode import Block, Interpreter
from hostd.sim.motion import Active, Traversed
from hostd.sim.probing import ProbeCycle, ToolSensor, TouchPlate, probe_input, sensor_surface
from hostd.sim.scanner import ControlLine, DataLine, Realtime
from hostd.sim.settings import BOARD_ID, JV_MAX, Settings

log = structlog.get_logger(__name__)

OUTPUT_BUFFER_LEN = 512  # controller.h: the buffer an answer is serialised into
INIT_MESSAGE = "Initializing configs to default settings"  # settings_default.h
LOADING_MESSAGE = "Loading configs from EEPROM"  # report.cpp
# States of a cycle under way, which ends in PROGRAM_STOP once nothing is left to run.
CYCLES = (MachineState.RUN, MachineState.HOMING, MachineState.PROBE)
# cmMachineState (`macs`) for each combined state [4].
# `spc` (101.03 spindle.h:49-53): 0 off, 1 CW, 2 CCW (3, paused in a hold, is not simulated).
_SPINDLE_STATE = {"M5": 0, "M3": 1, "M4": 2}
_MACS = {
    MachineState.INITIALIZING: 0,
    MachineState.READY: 1,
    MachineState.ALARM: 2,
    MachineState.PROGRAM_STOP: 3,
    MachineState.PROGRAM_END: 4,
    MachineState.INTERLOCK: 6,
    MachineState.SHUTDOWN: 7,
    MachineState.PANIC: 8,
}


class Hold(IntEnum):
    """g2core's `hold` values the simulator passes through [4]."""

    OFF = 0
    DECEL = 4  # decelerating to zero
    HOLD = 10  # standing in the hold


class Output:
    """The board's state and what it prints; the layers above call down into it.

    The state is declared here and set by `Board.__init__` and `Board.power_on`
    (board.py), which say what each part is for.
    """

    # Wiring, and the machine a test sets up: kept across a reset (Board.__init__).
    config: SimConfig
    _emit_line: Callable[[str], None]
    _clock: Callable[[], float]
    _request_reset: Callable[[], None]
    rx: dict[str, deque[DataLine]]
    _rx_bytes: dict[str, int]
    # Per port: its last line read was a control (xio.cpp `_last_returned_a_control`),
    # so the next `xio_flush_to_command` flushes it, up to that control: the data lines
    # that came in before it (`_flush_mark`, counted as `_rx_in`), not those behind it,
    # which the board's scan had not reached (xio.cpp:795-804, :1004).
    _control_last: dict[str, bool]
    _rx_in: dict[str, int]  # data lines ever queued on the port
    _rx_out: dict[str, int]  # of those, read or discarded
    _flush_mark: dict[str, int]  # `_rx_in` when the port's last control came in
    # Controls that came in on a data-only port, each with `_rx_in` as it came in,
    # read when that port is (board.py).
    rx_controls: dict[str, deque[tuple[Realtime | ControlLine, int]]]
    build: Build  # the rules of the firmware build this board is (g2builds.py)
    output_blocked: bool
    ack_delay: float
    refuse_next: int | None  # a test's: the next G-code line's status
    inputs: dict[str, float | int]
    unexposed: set[str]  # inputs whose `in<n>` GET answers null (board.py)
    probe_surface: tuple[str, float] | None
    tool_sensor: ToolSensor | None  # a fixed tool-length sensor (issue 29)
    tool_length: float  # how much longer the tool in the spindle is than the first, mm
    touch_plate: TouchPlate | None
    touch_reads: int  # the operator holds the plate to the bit for this many reads of it
    homing_failure: tuple[str, Status] | None
    output_buffer: int
    overflow_reported: bool
    glitches: dict[str, float]
    traversed: deque[Traversed]
    # What the firmware keeps: back to its start on every reset (Board.power_on).
    settings: Settings
    state: MachineState
    interp: Interpreter
    planner: deque[Block]
    _last_block_at: float
    _planner_running: bool
    active: Active | None
    position: dict[str, float]
    homed: dict[str, bool]
    hold: Hold
    _pending_exit: str | None
    _hold_point: dict[str, float] | None
    _p2: Interpreter | None
    interlock_input: bool
    interlocked: bool
    _ack: tuple[float, dict[str, Any]] | None
    _sr_last: dict[str, float | int]
    _sr_requested: bool
    _sr_now: bool
    _sr_next: float
    _qr_last: int | None
    _qi: int
    _qo: int
    _probing: ProbeCycle | None
    _init_message_due: bool

    # --- startup messages [10]

    def banner(self) -> None:
        """SYSTEM READY, the first line after every open [10]."""
        fb = self.config.fb
        if fb >= 400:  # TinyG's shape, four-element footer with a checksum [2]
            body = {"fv": 0.97, "fb": fb, "hp": 1, "hv": 8, "id": BOARD_ID}
            body["msg"] = "SYSTEM READY"
            head = _dumps({"r": body})[:-1] + ',"f":[1,0,1,'
            self._emit_line(f"{head}{_tinyg_checksum(head)}]}}")
            return
        self._startup_message(Status.OK, "SYSTEM READY")

    def boot_messages(self) -> None:
        """What a board prints as it boots, where a host can read it (a UART link).

        config_init() prints "Loading configs from EEPROM" (status 15), then
        SYSTEM READY (report.cpp); a native USB board prints them to nobody.
        """
        if self.config.fb < 400:
            self._startup_message(Status.INITIALIZING, LOADING_MESSAGE)
        self.banner()

    def _startup_message(self, status: Status, msg: str, count: int = 1) -> None:
        """report.cpp `_startup_helper`: an `{r}` of identity and `msg`, answering no line.

        Its count is cs.linelen + 1: 1 at boot, a line's own count when a line prints it.
        """
        body = self.settings.identity | {"msg": msg}
        self._emit({"r": body, "f": [1, int(status), count]})

    # --- exception reports [10]

    def _exception(self, status: Status, detail: str) -> None:
        msg = f"{message(status)} - {detail}"
        self._emit({"er": {"fb": self.config.fb, "st": int(status), "msg": msg}})

    # --- reports [2, 4, 6]

    @property
    def _jv(self) -> int:
        return int(self.settings["jv"])

    def _respond(
        self,
        body: dict[str, Any],
        status: Status,
        linelen: int,
        *,
        data: bool,
        n: int = 0,
    ) -> None:
        jv = self._jv
        if jv == 0 or (jv == JV_MAX and status == Status.OK):
            return
        if n and jv >= 4:
            body["n"] = n
        if self._init_message_due:
            # `{defa:1}` printed its startup message while the line ran: that took the
            # line's count, and json_print_response reset cs.linelen to 0.
            self._init_message_due = False
            self._startup_message(Status.INITIALIZING, INIT_MESSAGE, linelen + 1)
            linelen = 0
        if self.config.fb >= 400:  # TinyG 440: strlen(line)+1 and a checksum [2]
            count = linelen + 1 if data else linelen
            head = _dumps({"r": body})[:-1] + f',"f":[1,{int(status)},{count},'
            self._emit_line(f"{head}{_tinyg_checksum(head)}]}}")
            return
        obj = {"r": body, "f": [1, int(status), linelen + 1]}
        if len(_dumps(obj)) >= self.output_buffer:
            # json_print_response: an answer the board cannot hold is not printed; when
            # its nv list runs out it says so with an `er` 113 instead.
            if self.overflow_reported:
                self._exception(Status.JSON_OUTPUT_TOO_LONG, "json_print_response() json too long")
            return
        if data and self.ack_delay > 0:
            self._ack = (self._clock() + self.ack_delay, obj)
            return
        self._emit(obj)

    def _set_state(self, state: MachineState) -> None:
        if state != self.state:
            log.debug("sim board state", state=state.name)
            self.state = state
            self._sr_now = True
        if state not in CYCLES and state not in (MachineState.HOLD, MachineState.INTERLOCK):
            self._planner_running = False  # at rest, or locked out: the next move primes again

    def _at_rest_for_a_cycle(self) -> bool:
        return (
            self.state not in CYCLES
            and self.hold == Hold.OFF
            and not self.state.is_lockout
            and self.state is not MachineState.INTERLOCK
        )

    def _flush_sr(self) -> None:
        """State changes are reported at once, after the command that made them."""
        if self._sr_now:
            self._sr_now = False
            self._send_sr(self._clock())

    def _timed_reports(self, now: float) -> bool:
        if self.output_blocked:
            return False
        sent = False
        qv = int(self.settings["qv"])
        free = self._free
        if qv and self._jv and free != self._qr_last:
            self._qr_last = free
            report: dict[str, int] = {"qr": free}
            if qv == 2:
                report |= {"qi": self._qi, "qo": self._qo}
                self._qi = self._qo = 0
            self._emit(report)
            sent = True
        if (self._sr_requested or self._moving) and now >= self._sr_next:
            self._sr_requested = False
            self._sr_next = now + self.settings["si"] / 1000.0
            self._send_sr(now)
            sent = True
        return sent

    def _send_sr(self, now: float) -> None:
        sv = int(self.settings["sv"])
        if not sv:
            return
        values = self._values(now)
        body = reports.filtered(self.settings.sr_keys, values, self._sr_last, verbose=sv == 2)
        if body:
            self._emit({"sr": body})

    def _sr_full(self) -> dict[str, float | int]:
        values = self._values(self._clock())
        return {key: values[key] for key in self.settings.sr_keys}

    @property
    def _free(self) -> int:
        return max(self.config.planner_depth - len(self.planner), 0)

    @property
    def _moving(self) -> bool:
        return self.active is not None and self.active.move is not None

    def tool_position(self, now: float) -> dict[str, float]:
        return self.active.position(now) if self.active is not None else dict(self.position)

    def probe_closed(self) -> bool:
        """gpio_read_input(prbin): the digital input `prbin` names (gpio.cpp; input 0 reads
        false), closed by its wire, the surface or plate under the tool, or a touch."""
        n = int(self.settings["prbin"])
        if n == 0:
            return False
        return (
            bool(self.inputs[f"in{n}"])
            or self.touch_reads > 0
            or probe_input(self.probe_surface_here(), self.touch_plate, self.position)
        )

    def probe_surface_here(self) -> tuple[str, float] | None:
        """The tool sensor where the tool stands over it, else the test's surface."""
        return (
            sensor_surface(self.tool_sensor, self.tool_length, self.position) or self.probe_surface
        )

    def _values(self, now: float) -> dict[str, float | int]:
        """Every status report key's current value, rounded as reported."""
        interp = self.interp
        scale = interp.scale
        machine = self.tool_position(now)
        active = self.active
        velocity = active.velocity(now) if active is not None else 0.0
        running = active.block.n if active is not None else interp.line
        state = self.state
        cycle = 0
        if state in (MachineState.RUN, MachineState.HOLD, MachineState.INTERLOCK):
            cycle = 1
        elif state == MachineState.HOMING:
            cycle = 2
        elif state == MachineState.PROBE:
            cycle = 3
        values: dict[str, float | int] = {
            "line": running,
            "n": interp.line,
            "feed": (interp.feed or 0.0) / scale,
            "vel": velocity / scale,
            "unit": 1 if interp.metric else 0,
            "stat": int(state),
            "macs": _MACS.get(state, 5),
            "cycs": cycle,
            "mots": 1 if velocity > 0 else 0,
            "hold": int(self.hold),
            "coor": interp.coord,
            "dist": 0 if interp.absolute else 1,
            "admo": 1,
            "frmo": 0 if interp.inverse_time else 1,
            "momo": interp.motion if interp.motion is not None else 4,
            "plan": interp.plane - 17,
            "path": interp.path,
            "tool": interp.tool,
            "g92e": 1 if any(interp.offsets.values()) else 0,
            "home": 1 if all(self.homed.values()) else 0,
            "qr": self._free,
        }
        values |= self._spindle(active)
        values |= self.inputs
        if self.settings["prbin"]:
            values[f"in{int(self.settings['prbin'])}"] = int(self.probe_closed())
        offset = interp.work_offset()
        for axis in AXES:
            values[f"pos{axis}"] = (machine[axis] - offset[axis]) / scale
            values[f"mpo{axis}"] = machine[axis]
            values[f"ofs{axis}"] = offset[axis] / scale
            values[f"hom{axis}"] = 1 if self.homed[axis] else 0
        out = {key: reports.number(v, reports.places(key)) for key, v in values.items()}
        return out | self.glitches

    def _spindle(self, active: Active | None) -> dict[str, float | int]:
        """The spindle as the running move has it (g2core queues M3/M4/M5 with the moves),
        else as the last line read left it; in the keys of this board's build
        (reports.spindle_keys). 100.26's `spd` here follows M3/M4 only while on: the
        board keeps the last direction through an M5, which `spe` 0 makes moot."""
        move = active.move if active is not None else None
        spindle, speed = (
            (move.spindle, move.speed) if move else (self.interp.spindle, self.interp.speed)
        )
        if "spc" in self.settings.report_keys:
            return {"spc": _SPINDLE_STATE.get(spindle, 0), "sps": speed}
        on = spindle in ("M3", "M4")
        return {"spe": int(on), "spd": int(spindle == "M4"), "sps": speed}

    def _emit(self, obj: dict[str, Any]) -> None:
        self._emit_line(_dumps(obj))


def _dumps(obj: dict[str, Any]) -> str:
    """As the firmware serialises: floattoa() prints a NaN as `nan` and an
    infinity as `inf` or `-inf`, bare, where strict JSON has no word (util.cpp)."""
    text = json.dumps(obj, separators=(",", ":"))
    if "NaN" not in text and "Infinity" not in text:
        return text
    marked = json.dumps(_floattoa_marked(obj), separators=(",", ":"))
    return marked.replace('"\\u0001', "").replace('\\u0001"', "")


def _floattoa_marked(value: Any) -> Any:
    """Each non-finite float as its floattoa() word between two U+0001 (never in our text)."""
    if isinstance(value, float) and not math.isfinite(value):
        word = "nan" if math.isnan(value) else "-inf" if value < 0 else "inf"
        return f"\x01{word}\x01"
    if isinstance(value, dict):
        return {k: _floattoa_marked(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_floattoa_marked(v) for v in value]
    return value


def _tinyg_checksum(text: str) -> int:
    """TinyG 440's footer checksum: a Java-style string hash, mod 9999."""
    h = 0
    for ch in text:
        h = (31 * h + ord(ch)) & 0xFFFFFFFF
    return h % 9999
