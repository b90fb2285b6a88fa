"""`GrblSimController`: a simulated grbl / grblHAL board on a pseudo-terminal.

The same shell as the g2core `SimController` (hostd/sim/shell.py: the main
loop as one owned task, its lifecycle, waiting without sleeping, the kept
history) and the same pty machinery (hostd/sim/ptyport.py); what is grbl's
is here: one port behind a stable symlink, pins a test can toggle,
unplug/replug (a power-on), and the reset that opening the port may cause.
Every byte the host writes is handed to the board at once, as a UART
interrupt would: the board's receive ring, not the pty, decides what is kept
and what is lost.
"""

from __future__ import annotations

import asyncio
import contextlib
import time

import structlog

from hostd.sim.config import Received
from hostd.sim.grbl.board import GrblBoard
from hostd.sim.grbl.config import GrblConfig
from hostd.sim.probing import ToolSensor, TouchPlate
from hostd.sim.ptyport import PtyPort
from hostd.sim.shell import SimShell

log = structlog.get_logger(__name__)

EOL = b"\r\n"  # stream.h ASCII_EOL; gnea/grbl report.c
OPEN_FALLBACK = 0.05  # s to wait for the opener's tcflush before an open-reset anyway
PORT = "data"


class GrblSimController(SimShell[GrblBoard, str]):
    """A simulated grbl 1.1h or grblHAL; `async with GrblSimController(path) as sim:`.

    `received` holds chunks as read (kind "raw"); `sent`, lines written without the CRLF.
    """

    _what = "simulated grbl board"
    _name = "simulated grbl"

    def __init__(self, path: str, config: GrblConfig | None = None) -> None:
        self.config = config if config is not None else GrblConfig()
        super().__init__(self.config.history)
        self.path = path
        self._port: PtyPort | None = None
        self._attached = False
        self._open_pending = False  # reset-on-open waits for the opener's flush
        self._open_timer: asyncio.TimerHandle | None = None
        self._hung = False
        self.opens = 0  # times the port was opened (each resets an Arduino)
        self._board = GrblBoard(self.config, emit=self._emit, clock=time.monotonic)

    # --- lifecycle (start and close are the shell's)

    async def stop(self) -> None:
        """Stop the board, close the pty and remove the symlink: `close()`."""
        await self.close()

    def _plug_ports(self) -> None:
        self._port = PtyPort(PORT, self.path, self)
        self._port.plug()

    def _task_name(self) -> str:
        return f"grbl {self.path}"

    def _log_started(self) -> None:
        log.info("grbl sim started", path=self.path, flavour=self.config.flavour)

    def _log_crash(self) -> None:
        log.exception("grbl sim crashed", path=self.path)

    async def _shut_down(self) -> Exception | None:
        """Cancel the main loop and unplug; a cancellation of our own caller is swallowed."""
        self._cancel_open_timer()
        result: Exception | None = None
        if self._main_task is not None:
            self._main_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                try:
                    await self._main_task
                except Exception as exc:
                    result = exc
        if self._port is not None:
            self._port.unplug()
        return result

    # --- what tests look at

    @property
    def board(self) -> GrblBoard:
        """The firmware model itself (read it; drive it through this controller)."""
        return self._board

    @property
    def state(self) -> str:
        """The state as `?` names it (`Idle`, `Run`, `Hold:0`, `Door:1`, `Alarm`, ...)."""
        return self._board._state_text()

    @property
    def position(self) -> dict[str, float]:
        return self._board.tool_position()

    @property
    def attached(self) -> bool:
        return self._attached

    # --- waiting (wait_for and wait_state are the shell's)

    def _situation(self) -> str:
        return f"state {self.state}"

    async def wait_attached(self, timeout: float = 5.0) -> None:
        await self.wait_for(lambda: self._attached and not self._open_pending, timeout)

    # --- pins and cables

    def limit_switch(self, axis: str = "x", active: bool = True) -> None:
        """A limit switch closes (or opens): with $21=1 closing it is ALARM:1."""
        self._board.set_limit(axis.lower(), active)
        self._kick()

    def estop(self, active: bool) -> None:
        """grblHAL's e-stop input: ALARM:10 while moving or not; 0x18 refused while held."""
        self._board.set_estop(active)
        self._kick()

    def door(self, active: bool) -> None:
        """The safety door input: open stops into Door, closed lets `~` resume."""
        self._board.set_door(active)
        self._kick()

    def probe(self, active: bool) -> None:
        """The probe input: contact (True) ends a G38.2 cycle with [PRB:...:1]."""
        self._board.set_probe(active)
        self._kick()

    def tool_sensor(self, x: float, y: float, z: float) -> None:
        """A fixed tool-length sensor at machine X, Y: a G38.2 that starts over it (within
        1 mm) closes the probe input at machine Z `z` plus the tool's length."""
        self._board.tool_sensor = ToolSensor(float(x), float(y), float(z))

    def tool_length(self, mm: float) -> None:
        """The operator put in a tool `mm` longer than the first (it trips the sensor higher)."""
        self._board.tool_length = float(mm)

    def touch_plate(self, plate: TouchPlate | None) -> None:
        """A touch plate on the work, wired to the probe pin; None takes it away.

        The pin reads closed (`Pn:P`) wherever the bit touches it
        (probing.TouchPlate), and a G38.x move ends where it meets it. Kept across resets.
        """
        self._board.touch_plate = plate
        self._kick()

    def touch(self, reads: int = 1) -> None:
        """The operator holds the plate to the bit: `Pn:P` in the next `reads` status
        reports, then the pin opens as they let go."""
        if reads < 0:
            raise ValueError("reads is 0 or more")
        self._board.touch_reads = reads
        self._kick()

    def lose_status_requests(self, count: int = 1) -> None:
        """The wire loses the next `count` `?` bytes (line noise, a USB-serial adapter)."""
        self._board.status_lost += count

    def report_overrides_next(self) -> None:
        """The override counter runs out: the next report carries `Ov:`, as one in every
        10 or 20 does (report.c report_realtime_status, sys.report_ovr_counter)."""
        self._board._ovr_counter = 0

    def ignore_status_requests(self, ignored: bool = True) -> None:
        """`?` gets no report while lines still get their `ok` (reports stop, answers go on)."""
        self._board.status_ignored = ignored

    def refuse_next(self, code: int) -> None:
        """The next G-code line is answered `error:<code>` and not run: any of grblHAL's
        errors.h, including those this simulator's firmware model never gives."""
        self._board.refuse_next = code

    def queue_input(self, queued: bool = True) -> None:
        """The host's bytes wait unread (realtime ones too) while `queued`; then they are
        read a byte a main-loop pass, in order, as grblHAL's upstream Simulator reads
        (`GrblBoard.queue_input`): the `?`s the host asked again each get a late report."""
        self._board.queue_input(queued)
        self._kick()

    def hang(self, hung: bool = True) -> None:
        """The firmware hangs with its USB device still there: it reads and prints nothing."""
        self._hung = hung
        self._kick()

    def inject_garbage(self, data: bytes) -> None:
        """Write `data` raw to the host, as a noisy or broken board might."""
        if self._port is not None and self._port.write(data):
            self._keep(self.sent, Received(time.monotonic(), PORT, data, "raw"))
            self._pulse()

    def flash(self, config: GrblConfig) -> None:
        """Another build of the same firmware flavour, from the board's next power-up on
        (`replug`; the host reads it at its handshake). For a build option the board
        reads as it runs, as `line_numbers` (USE_LINE_NUMBERS) is."""
        if config.flavour != self.config.flavour or config.rx_size != self.config.rx_size:
            raise ValueError("flash a build of the same flavour and receive buffer")
        self.config = self._board.config = config

    async def unplug(self) -> None:
        """Pull the USB cable: the host reads EOF/EIO, the symlink goes away."""
        if self._port is not None:
            self._port.unplug()
        self._kick()

    async def replug(self) -> None:
        """Plug it back: the board powers up afresh behind the same path."""
        if self._closed or self._port is None:
            return
        self._board.power_on()
        self._port.plug()
        self._kick()

    # --- the port listener (called by PtyPort)

    def port_attached(self, port: PtyPort) -> None:
        self._attached = True
        self.opens += 1
        port.set_read_limit(1 << 16)
        if self.config.opens_with_reset:
            # An Arduino's DTR resets the board; its banner must come after the opener's
            # tcflush, or the flush throws it away (see hostd/sim/controller.py).
            self._open_pending = True
            self._cancel_open_timer()
            loop = asyncio.get_running_loop()
            self._open_timer = loop.call_later(OPEN_FALLBACK, self._open_reset)
        self._kick()

    def port_detached(self, port: PtyPort) -> None:
        self._attached = False
        self._open_pending = False
        self._cancel_open_timer()
        self._kick()

    def port_flushed(self, port: PtyPort) -> None:
        if self._open_pending:
            self._open_reset()

    def port_data(self, port: PtyPort, data: bytes) -> None:
        port.set_read_limit(1 << 16)
        if self._open_pending or self._hung:
            return  # the board is still in its bootloader, or hangs
        self._keep(self.received, Received(time.monotonic(), PORT, data, "raw"))
        self._board.receive(data)
        self._kick()

    def port_drained(self, port: PtyPort) -> None:
        self._kick()

    # --- internals

    def _open_reset(self) -> None:
        self._cancel_open_timer()
        if not self._open_pending:
            return
        self._open_pending = False
        self._board.power_on()
        self._kick()

    def _cancel_open_timer(self) -> None:
        if self._open_timer is not None:
            self._open_timer.cancel()
            self._open_timer = None

    def _emit(self, line: str) -> None:
        port = self._port
        if port is None or not self._attached or self._open_pending or self._hung:
            return  # a board with nobody listening talks to nobody; a hung one to nobody
        data = line.encode("latin-1", "replace")
        if port.write(data + EOL):
            self._keep(self.sent, Received(time.monotonic(), PORT, data, "line"))

    def _halted(self) -> bool:
        """Only while `hang()` holds it; its resets run inside the board."""
        return self._hung

    def _read_waiting(self) -> None:
        if self._port is not None and not self._open_pending:  # an open: the loop's, as g2core's
            self._port.read_waiting()

    def _update_reading(self) -> None:
        """Nothing to re-plan: the port reads all it can (port_attached, port_data) and
        the board's receive ring, not the pty, decides what is kept."""
