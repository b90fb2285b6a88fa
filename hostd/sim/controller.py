"""`SimController`: a simulated g2core board on one or two pseudo-terminals.

It glues the pieces together and is the API that tests, `make demo` and a
machine configured with `data_port = "sim"` use: ports (ptyport.py) bring
bytes in, the scanner (scanner.py) splits them as the board's RX buffer
does, the board model (board.py) answers; this file routes the answers to
the port that has the control role, runs the board's main loop as one owned
task (in the shell shared with the grbl board, shell.py), and offers
injections (limit switch, e-stop, unplug, ...) and ways to wait for what the
board saw or did.

Roles follow g2core's dual-endpoint USB (g2core.md section 9): the first
port a host opens is control and data and receives all output; a second one
opened while it is open is data only and never receives anything. Closing
the control port while the other stays open leaves that other one inactive
(not read, never written) until it is closed and opened again, as
g2core's `connectedStateChanged` does.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable

import structlog

from hostd.protocol.states import MachineState
from hostd.protocol.status import Status
from hostd.sim.board import Board
from hostd.sim.callsites import CallSite
from hostd.sim.config import AXES, Kind, Received, SimConfig
from hostd.sim.probing import ToolSensor, TouchPlate
from hostd.sim.ptyport import PtyPort
from hostd.sim.reports import ANALOG_INPUTS, DIGITAL_INPUTS
from hostd.sim.scanner import ControlLine, DataLine, LineScanner, NulFlush, Realtime
from hostd.sim.shell import SimShell

log = structlog.get_logger(__name__)

BANNER_FALLBACK = 0.05  # s to wait for the opener's tcflush before sending the banner anyway
DATA, CONTROL = "data", "control"


class SimController(SimShell[Board, MachineState]):
    """A simulated g2core; `async with SimController(path) as sim:` plugs it in."""

    _what = _name = "simulated board"

    def __init__(
        self,
        data_path: str,
        control_path: str | None = None,
        config: SimConfig | None = None,
    ) -> None:
        self.config = config if config is not None else SimConfig()
        super().__init__(self.config.history)
        self._paths = {DATA: data_path}
        if control_path is not None:
            self._paths[CONTROL] = control_path
        self._board = Board(self.config, emit=self._emit, clock=time.monotonic, reset=self._reboot)
        self._ports: dict[str, PtyPort] = {}
        self._scanners = {name: LineScanner(self._board.percent_is_control) for name in self._paths}
        self._active: set[str] = set()  # attached ports the board reads
        self._primary: str | None = None  # the port with the control role
        self._banner = "done"  # for the current open: pending, fallback or done
        self._banner_at = 0  # the control port's `written` count when its banner went out
        self._banner_boot = False  # this open's banner is a UART board's boot messages
        self._banner_timer: asyncio.TimerHandle | None = None
        self._reading = True
        self._silent = False
        self._resetting = False
        self._booted = False  # a UART board prints its banner once after a boot
        self._reset_task: asyncio.Task[None] | None = None

    # --- lifecycle (start and close are the shell's)

    def _plug_ports(self) -> None:
        """Create the pty pairs and symlinks; if one fails, none stays."""
        self._ports = {name: PtyPort(name, path, self) for name, path in self._paths.items()}
        try:
            for port in self._ports.values():
                port.plug()
        except BaseException:
            for port in self._ports.values():
                port.unplug()
            raise

    def _task_name(self) -> str:
        return f"sim-board {self.data_path}"

    def _log_started(self) -> None:
        log.info("sim board started", data=self.data_path, control=self.control_path)

    def _log_crash(self) -> None:
        log.exception("sim board crashed", data=self.data_path)

    async def _shut_down(self) -> Exception | None:
        """Cancel the main loop and a reset under way; the ptys go even if we are cancelled."""
        tasks = [t for t in (self._main_task, self._reset_task) if t is not None]
        for task in tasks:
            task.cancel()
        try:
            results = await asyncio.gather(*tasks, return_exceptions=True)
        finally:
            self._cancel_banner()
            for port in self._ports.values():
                port.unplug()
            log.info("sim board closed", data=self.data_path)
        return next((r for r in results if isinstance(r, Exception)), None)

    # --- what tests look at

    @property
    def data_path(self) -> str:
        return self._paths[DATA]

    @property
    def control_path(self) -> str | None:
        return self._paths.get(CONTROL)

    @property
    def state(self) -> MachineState:
        return self._board.state

    @property
    def line(self) -> int:
        """The line number its reports give as `line`: the block it runs, else the last read."""
        board = self._board
        active = board.active
        return active.block.n if active is not None else board.interp.line

    @property
    def position(self) -> dict[str, float]:
        """Machine position in mm, where the tool is right now."""
        return self._board.tool_position(time.monotonic())

    @property
    def homed(self) -> bool:
        return all(self._board.homed.values())

    @property
    def planner_len(self) -> int:
        """Blocks in the planner, the one being executed included."""
        return len(self._board.planner)

    def attached(self, port: str | None = None) -> bool:
        """Whether a host has `port` (default: any port) open."""
        ports = [self._ports[port]] if port is not None else list(self._ports.values())
        return any(p.attached for p in ports)

    # --- waiting, without sleeping (wait_for and wait_state are the shell's)

    def _situation(self) -> str:
        return (
            f"state {self.state.name}, planner {self.planner_len}, "
            f"{len(self.received)} received, {len(self.sent)} sent"
        )

    async def wait_attached(self, timeout: float = 5.0, port: str | None = None) -> None:
        await self.wait_for(lambda: self.attached(port), timeout)

    async def wait_received(self, what: bytes | Callable[[], bool], timeout: float = 5.0) -> None:
        """Wait for a line (or realtime byte) equal to `what`, or for a predicate."""
        if isinstance(what, bytes):
            wanted = what
            await self.wait_for(lambda: any(r.data == wanted for r in self.received), timeout)
        else:
            await self.wait_for(what, timeout)

    # --- injections

    def limit_switch(self, axis: str = "x") -> None:
        """A limit switch trips: ALARM 203, the machine is unhomed (if `lim` is on)."""
        self._board.limit_switch(axis)
        self._kick()

    def interlock(self, active: bool) -> None:
        """The safety interlock input: a halt into state 11 while active."""
        self._board.interlock(active)
        self._kick()

    def estop(self, active: bool) -> None:
        """The e-stop input: SHUTDOWN 5 when it becomes active; releasing clears nothing."""
        self._board.estop(active)
        self._kick()

    def panic(self) -> None:
        self._board.panic()
        self._kick()

    def set_homed(self, homed: bool) -> None:
        self._board.set_homed(homed)
        self._kick()

    def firmware_exception(self, site: CallSite) -> None:
        """The firmware calls cm_alarm / cm_shutdown / cm_panic as at `site` (callsites.py)."""
        self._board.firmware_exception(site.status, site.path, site.detail)
        self._kick()

    def fail_homing(self, axis: str | None, status: int = Status.HOMING_CYCLE_FAILED) -> None:
        """Homing `axis` fails from now on with `status` (240-247); None: homing works.

        As cycle_homing.cpp `_homing_error_exit` does: an extra `{r}` with status
        240 and the reason, no alarm, the axis not homed; the next lines run.
        """
        if axis is not None and axis not in AXES:
            raise ValueError(f"no axis {axis!r}: the board has {', '.join(AXES)}")
        self._board.homing_failure = None if axis is None else (axis, Status(status))
        self._kick()

    def probe_surface(self, axis: str | None, at: float = 0.0) -> None:
        """The probe touches a surface at `at` (machine mm) on `axis`; None removes it.

        A G38.2/G38.3 probe trips where its move reaches the surface; G38.4/G38.5
        trip as the tool leaves it. Kept across resets (it is the workpiece).
        """
        if axis is not None and axis not in AXES:
            raise ValueError(f"no axis {axis!r}: the board has {', '.join(AXES)}")
        self._board.probe_surface = None if axis is None else (axis, float(at))
        self._kick()

    def tool_sensor(self, x: float, y: float, z: float) -> None:
        """A fixed tool-length sensor at machine X, Y: a G38.2 that starts over it (within
        1 mm) trips at machine Z `z` plus the tool's length (`tool_length`)."""
        self._board.tool_sensor = ToolSensor(float(x), float(y), float(z))
        self._kick()

    def tool_length(self, mm: float) -> None:
        """The operator put in a tool `mm` longer than the first (it trips the sensor higher)."""
        self._board.tool_length = float(mm)

    def touch_plate(self, plate: TouchPlate | None) -> None:
        """A touch plate on the work, wired to the probe input (`prbin`); None takes it away.

        The input reads closed wherever the bit touches it (probing.TouchPlate), in
        the status reports and `{inN:n}` as in G38.x. Kept across resets.
        """
        self._board.touch_plate = plate
        self._kick()

    def touch(self, reads: int = 1) -> None:
        """The operator holds the plate to the bit: the probe input reads closed for the
        next `reads` reads of `in<prbin>` (`{in5:n}`), then opens as they let go."""
        if reads < 0:
            raise ValueError("reads is 0 or more")
        self._board.touch_reads = reads
        self._kick()

    def set_output_buffer(self, size: int, *, reported: bool = True) -> None:
        """Answers of `size` bytes or more are not printed: an `er` 113 instead, or nothing.

        json_print_response() sends 113 when the answer does not fit its list; an
        answer that is simply lost (`reported=False`) is the other way a board fails.
        """
        self._board.output_buffer = size
        self._board.overflow_reported = reported
        self._kick()

    def glitch(self, key: str, value: float | None) -> None:
        """Status key `key` reads `value` (`math.nan`, `math.inf`), printed bare as the
        firmware's floattoa() prints it; None ends it."""
        self._board.glitch(key, value)
        self._kick()

    def set_input(self, n: int, value: int | bool) -> None:
        """Digital input `n` (1..8) reads `value` (0/1): `in<n>`, reported when listed."""
        if not _input_number(n, DIGITAL_INPUTS):
            raise ValueError(f"no digital input {n!r}: the board has in1..in{DIGITAL_INPUTS}")
        if value not in (0, 1) or isinstance(value, float):
            raise ValueError(f"a digital input is 0 or 1, not {value!r}")
        self._board.set_input(f"in{n}", int(value))
        self._kick()

    def unexpose_input(self, n: int) -> None:
        """Digital input `n` is forwarded to no `in<n>` reader (its `di<n>in` is another
        number): `{"in<n>":null}` answers null (g2core gpio.h, the reader's getState
        with no pin), while G38.x still reads the pin (gpio_read_input, gpio.cpp)."""
        if not _input_number(n, DIGITAL_INPUTS):
            raise ValueError(f"no digital input {n!r}: the board has in1..in{DIGITAL_INPUTS}")
        self._board.unexposed.add(f"in{n}")

    def set_analog(self, n: int, value: float) -> None:
        """Analogue input `n` (1..4) reads `value`: `ain<n>`, reported when listed."""
        if not _input_number(n, ANALOG_INPUTS):
            raise ValueError(f"no analogue input {n!r}: the board has ain1..ain{ANALOG_INPUTS}")
        if isinstance(value, bool) or not math.isfinite(value):
            raise ValueError(f"an analogue input reads a finite number, not {value!r}")
        self._board.set_input(f"ain{n}", float(value))
        self._kick()

    @property
    def inputs(self) -> dict[str, float | int]:
        """What each input reads now, by status report key (`in1`.., `ain1`..)."""
        return dict(self._board.inputs)

    def inject_garbage(self, data: bytes) -> None:
        """Write `data` raw to the port with the control role, as a broken board might."""
        port = self._output_port()
        if port is not None and port.write(data):
            self._keep(self.sent, Received(time.monotonic(), port.name, data, "raw"))
            self._pulse()

    def refuse_next(self, status: int) -> None:
        """The next G-code line is answered with `status` (any of error.h's) and not run."""
        self._board.refuse_next = int(Status(status))

    def set_ack_delay(self, seconds: float) -> None:
        """Each data line's response goes out this much later (the board reads on after it)."""
        self._board.ack_delay = max(seconds, 0.0)
        self._kick()

    def stop_reading(self) -> None:
        """Take no more bytes from the host: its writes back up in the kernel."""
        self._reading = False
        self._kick()

    def resume_reading(self) -> None:
        self._reading = True
        self._kick()

    def go_silent(self, silent: bool) -> None:
        """Hang (True): send nothing, read nothing, run nothing, but keep the ports."""
        self._silent = silent
        self._kick()

    async def unplug(self) -> None:
        """Pull the USB cable: the host reads EOF/EIO, the symlinks go away."""
        for port in self._ports.values():
            port.unplug()
        self._kick()

    async def replug(self) -> None:
        """Plug the cable back: new ptys behind the same paths, a banner on the next open."""
        if self._closed:
            return
        for port in self._ports.values():
            port.plug()
        self._kick()

    async def reset(self) -> None:
        """Reset the board as 0x18 does: it goes away, boots, and comes back fresh."""
        self._reboot()
        if self._reset_task is not None:
            await asyncio.shield(self._reset_task)

    # --- the port listener (called by PtyPort from the event loop)

    def port_attached(self, port: PtyPort) -> None:
        name = port.name
        self._scanners[name].reset()
        self._board.open_rx(name)
        if not self._active:
            # The first port opened becomes control and data [9].
            self._primary = name
            self._board.connected()
            self._cancel_banner()
            if not self.config.uart or self._booted:
                self._banner_boot = self.config.uart and self._booted
                self._booted = False
                self._banner = "pending"
                loop = asyncio.get_running_loop()
                self._banner_timer = loop.call_later(BANNER_FALLBACK, self._banner_fallback)
            else:
                self._banner = "done"  # it booted long ago, and said so to nobody
        self._active.add(name)
        self._kick()

    def port_detached(self, port: PtyPort) -> None:
        name = port.name
        self._scanners[name].reset()
        self._board.close_rx(name)
        self._active.discard(name)
        if name == self._primary:
            self._primary = None
            self._cancel_banner()
            for other in self._active:  # the other port, if open, is deactivated [9]
                self._board.close_rx(other)
            self._active.clear()
        if self._board.output_blocked and self._output_port() is None:
            self._board.output_blocked = False
        if not any(p.attached for p in self._ports.values()):
            self._board.disconnected()
        self._kick()

    def port_flushed(self, port: PtyPort) -> None:
        """The opener's tcflush: it discarded what was written before, so now the banner.

        Only the first flush of an open brings it: a host may flush again whenever it
        likes (a TCIOFLUSH read as two packets, `tty.setraw` then tcflush, a reset of
        its input), and that is no new open; a reopen the port has already reported
        (`PtyPort`, counting opens with inotify) before this flush.
        """
        if port.name not in self._active or port.name != self._primary:
            return
        if self._banner == "done":
            return
        self._cancel_banner()
        fallback = self._banner == "fallback"
        self._banner = "done"
        if fallback and port.unread() >= port.written - self._banner_at:
            # The fallback banner went out before this flush was made (the timer took
            # any flush made before it first, `_banner_fallback`, so this one came in
            # the moment between that look and the write): the host still has it.
            return
        # No banner yet, or the flush threw the fallback one away: send it now.
        self._send_banner(port)
        self._kick()

    def port_data(self, port: PtyPort, data: bytes) -> None:
        name = port.name
        if name not in self._active or self._resetting:
            return
        board = self._board
        if name == self._primary and self._banner == "fallback":
            # The host writes: its open is over. A flush from now on is its own business
            # (it has read the banner, or flushes it away as it would a real board's).
            self._banner = "done"
        # A data-only port (the second one opened) is read only when the board reads
        # data: its controls wait there, ahead of its data lines (xio.cpp readline).
        data_only = name != self._primary
        for event in self._scanners[name].feed(data):
            now = time.monotonic()
            if isinstance(event, Realtime):
                self._record(now, name, bytes([event.char]), "realtime")
                if data_only:
                    board.queue_control(name, event)
                else:
                    board.realtime(name, event.char)
            elif isinstance(event, ControlLine):
                self._record(now, name, event.text, "line")
                if data_only:
                    board.queue_control(name, event)
                else:
                    board.control(event.text, event.linelen, name)
            elif isinstance(event, DataLine):
                self._record(now, name, event.text, "line")
                board.queue_line(name, event)
            elif isinstance(event, NulFlush):
                board.discard_rx(name)
            if self._resetting or name not in self._active:
                break
        self._kick()

    def port_drained(self, port: PtyPort) -> None:
        if port.name == self._primary:
            self._board.output_blocked = False
        self._kick()

    # --- internals

    def _record(self, t: float, port: str, data: bytes, kind: Kind) -> None:
        self._keep(self.received, Received(t, port, data, kind))

    def _output_port(self) -> PtyPort | None:
        if self._silent or self._resetting or self._primary is None:
            return None
        if self._banner == "pending":
            return None  # nothing goes out before the banner (nothing the opener would keep)
        port = self._ports.get(self._primary)
        return port if port is not None and port.attached else None

    def _emit(self, line: str) -> None:
        port = self._output_port()
        if port is None:
            return
        data = line.encode("ascii", "backslashreplace")
        if port.write(data + b"\n"):
            self._keep(self.sent, Received(time.monotonic(), port.name, data, "line"))
            if port.backlog:
                self._board.output_blocked = True
            self._pulse()

    def _banner_fallback(self) -> None:
        """An opener that does not flush (a plain open) still gets its banner."""
        self._banner_timer = None
        port = self._ports.get(self._primary) if self._primary is not None else None
        if self._banner != "pending" or port is None:
            return
        if port.take_flush():
            return  # the opener did flush, before now: `port_flushed` sent the banner
        # Any flush read from here on was made after this look: it threw this banner
        # away, unless made in the moment before the write (`port_flushed` asks the pty).
        self._banner = "fallback"
        self._send_banner(port)
        self._kick()

    def _send_banner(self, port: PtyPort) -> None:
        """SYSTEM READY; after a UART board's boot, its boot messages (report.cpp)."""
        self._banner_at = port.written
        if self._banner_boot:
            self._board.boot_messages()
        else:
            self._board.banner()

    def _cancel_banner(self) -> None:
        if self._banner_timer is not None:
            self._banner_timer.cancel()
            self._banner_timer = None

    def _reboot(self) -> None:
        """0x18 or `reset()`: unplug now, come back after the boot time."""
        if self._resetting or self._closed:
            return
        self._resetting = True
        log.info("sim board reset", data=self.data_path)
        self._reset_task = asyncio.get_running_loop().create_task(
            self._boot(), name=f"sim-board reset {self.data_path}"
        )

    async def _boot(self) -> None:
        try:
            for port in self._ports.values():
                port.unplug()
            await asyncio.sleep(self.config.boot_time)
            self._board.power_on()
            self._booted = True
            for scanner in self._scanners.values():
                scanner.reset()
        finally:
            self._resetting = False
        if not self._closed:
            for port in self._ports.values():
                port.plug()
        self._kick()

    def _read_waiting(self) -> None:
        for name, port in self._ports.items():
            if name in self._active:
                port.read_waiting()

    def _update_reading(self) -> None:
        """Read from each open port as much as its RX budget allows (0 = stop)."""
        budget = self.config.rx_budget
        for name, port in self._ports.items():
            if not port.attached:
                continue
            limit = 0
            if self._reading and not self._silent and not self._resetting and name in self._active:
                used = self._board.rx_bytes(name) + self._scanners[name].partial
                limit = budget - used
            port.set_read_limit(limit)

    def _halted(self) -> bool:
        """A hung board (`go_silent`) or one resetting runs nothing and waits for no deadline."""
        return self._silent or self._resetting


def _input_number(n: object, count: int) -> bool:
    return isinstance(n, int) and not isinstance(n, bool) and 1 <= n <= count
