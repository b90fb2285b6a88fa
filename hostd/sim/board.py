"""The simulated g2core: settings, machine state, planner, and every answer it gives.

This is the firmware's main loop without the hardware: the controller feeds
it scanned input (controls at once, data lines into per-port RX queues) and
calls `tick()` until it reports no progress, then sleeps until
`next_deadline()` or new input. Output leaves as text lines through `emit`.
No I/O and no asyncio here; the clock is injected.

Which g2core behaviour each part follows is cited from ../shared/spec/g2core.md
(sections in brackets).

`Board` is one class written in layers, a file each. A layer calls only
itself and the layers below it, and none overrides another:

    board.py     Board      construction, power and connection, the controller's
                            inputs and injections, the main loop
    commands.py  Commands   data lines, JSON and text commands, settings, G-code
    planner.py   Planner    the planner and motion, homing that fails, a probe's start
    stops.py     Stops      realtime controls, holds, flush, kill, lockouts, a probe's end
    intake.py    Intake     which data line is read next, and the flush to the command
    output.py    Output     the board's state, declared once; answers and reports

probing.py holds the probe input's geometry, which needs none of the state.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

from hostd.protocol.g2builds import Build
from hostd.protocol.states import MachineState
from hostd.protocol.status import Status
from hostd.sim import reports
from hostd.sim.commands import Commands
from hostd.sim.config import AXES, SimConfig
from hostd.sim.gcode import Interpreter
from hostd.sim.output import OUTPUT_BUFFER_LEN, Hold
from hostd.sim.planner import BLOCK_TIMEOUT
from hostd.sim.scanner import ControlLine, DataLine, Realtime
from hostd.sim.settings import Settings

__all__ = ["BLOCK_TIMEOUT", "Board"]  # BLOCK_TIMEOUT lives in planner.py

INPUTS = {"x": 1, "y": 3, "z": 5}  # limit switch input numbers, for `er` details
ESTOP_INPUT, PANIC_INPUT = 7, 9
# What cm_alarm / cm_shutdown / cm_panic each leave the machine in (alarm.cpp).
_LOCKOUT_PATHS = {
    "alarm": MachineState.ALARM,
    "shutdown": MachineState.SHUTDOWN,
    "panic": MachineState.PANIC,
}


class Board(Commands):
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
        self.build = Build(config.fb)
        self.rx = {}
        self._rx_bytes = {}
        self._control_last = {}
        self._rx_in = {}
        self._rx_out = {}
        self._flush_mark = {}
        self.rx_controls = {}
        self.output_blocked = False  # the host stopped reading; the main loop stalls
        self.ack_delay = 0.0
        # The next G-code line is answered with this status instead of run (a test's: a
        # status the firmware gives only for a file, a build or a machine hostd lacks).
        self.refuse_next: int | None = None
        # Input pins are wired to the machine, not kept by the firmware: a reset keeps them.
        self.inputs = dict.fromkeys(reports.INPUT_KEYS, 0)
        # Inputs no `in<n>` reader is forwarded to: their GET answers null (g2core gpio.h,
        # gpioDigitalInputReader::getState with no pin), while G38.x still reads the pin
        # (gpio_read_input, gpio.cpp): a board that cannot show its probe input.
        self.unexposed: set[str] = set()
        # So is the rest of the machine a test sets up: a reset keeps these too.
        self.probe_surface = None  # axis, machine mm the probe touches
        self.tool_sensor = None  # a fixed tool-length sensor (probing.ToolSensor)
        self.tool_length = 0.0  # the tool in the spindle: mm longer than the first
        self.touch_plate = None  # the touch plate on the work (probing.TouchPlate)
        self.touch_reads = 0
        self.homing_failure = None  # axis, why homing it fails
        self.output_buffer = OUTPUT_BUFFER_LEN  # answers this long or longer are not printed
        self.overflow_reported = True  # as an `er` 113, or (False) not at all
        self.glitches = {}  # status values computed wrong (nan, inf), by key
        # Every move the machine made, in order (motion.Traversed): a test's record of
        # where the tool went, kept across resets like the machine itself.
        self.traversed = deque(maxlen=config.history)
        self.power_on()

    # --- power and connection

    def power_on(self) -> None:
        """The state after a reset: READY, unhomed, nothing queued, default settings."""
        self.settings = Settings(self.config)
        self.state = MachineState.READY
        # G54..G59 are persistent settings: they outlive a reset (config.cpp, NVM).
        kept = self.interp.coords if hasattr(self, "interp") else None
        self.interp = Interpreter() if kept is None else Interpreter(coords=kept)
        self.planner = deque()
        self._last_block_at = 0.0  # when the last block went into the planner
        self._planner_running = False  # PLANNER_IDLE/STARTUP (False) or moving blocks (True)
        self.active = None
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
            self._control_last[port] = False

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
        self._control_last[port] = False
        self._rx_in[port] = self._rx_out[port] = self._flush_mark[port] = 0
        self.rx_controls[port] = deque()

    def close_rx(self, port: str) -> None:
        self.rx.pop(port, None)
        self._rx_bytes.pop(port, None)
        self._control_last.pop(port, None)
        for counts in (self._rx_in, self._rx_out, self._flush_mark):
            counts.pop(port, None)
        self.rx_controls.pop(port, None)

    def rx_bytes(self, port: str) -> int:
        """Bytes of data lines waiting in `port`'s RX buffer."""
        return self._rx_bytes.get(port, 0)

    def queue_line(self, port: str, line: DataLine) -> None:
        queue = self.rx.get(port)
        if queue is not None:
            queue.append(line)
            self._rx_bytes[port] += line.size
            self._rx_in[port] += 1

    def queue_control(self, port: str, event: Realtime | ControlLine) -> None:
        """A control that came in on a data-only port: it waits until the board reads
        that port (`_dispatch_command`), and is then read ahead of the port's data lines."""
        queue = self.rx_controls.get(port)
        if queue is not None:
            queue.append((event, self._rx_in[port]))  # the data lines that came before it

    def control(self, text: bytes, linelen: int, port: str = "") -> None:
        """A `{...}` control line, run ahead of queued data lines [7.1]."""
        self._control_line(text, linelen, port)

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
