"""`GrblSimController`: a simulated grbl / grblHAL board on a pseudo-terminal.

The same shape as the g2core `SimController` (hostd/sim/controller.py) and
the same pty machinery (hostd/sim/ptyport.py): one port behind a stable
symlink, the pure board (board.py) run by one owned task, pins a test can
toggle, unplug/replug, and ways to wait for what the board did without
sleeping. Every byte the host writes is handed to the board at once, as a
UART interrupt would: the board's receive ring, not the pty, decides what
is kept and what is lost.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable
from types import TracebackType

import structlog

from hostd.sim.config import Received
from hostd.sim.grbl.board import GrblBoard
from hostd.sim.grbl.config import GrblConfig
from hostd.sim.ptyport import PtyPort

log = structlog.get_logger(__name__)

EOL = b"\r\n"  # stream.h ASCII_EOL; gnea/grbl report.c
MAX_STEPS = 512
OPEN_FALLBACK = 0.05  # s to wait for the opener's tcflush before an open-reset anyway
PORT = "data"


class GrblSimController:
    """A simulated grbl 1.1h or grblHAL; `async with GrblSimController(path) as sim:`."""

    def __init__(self, path: str, config: GrblConfig | None = None) -> None:
        self.config = config if config is not None else GrblConfig()
        self.path = path
        self.received: list[Received] = []  # chunks as read (kind "raw")
        self.sent: list[Received] = []  # lines written, without the CRLF
        self._port: PtyPort | None = None
        self._attached = False
        self._open_pending = False  # reset-on-open waits for the opener's flush
        self._open_timer: asyncio.TimerHandle | None = None
        self._wake: asyncio.Event | None = None
        self._changed: asyncio.Event | None = None
        self._task: asyncio.Task[None] | None = None
        self._closed = False
        self._board = GrblBoard(self.config, emit=self._emit, clock=time.monotonic)

    # --- lifecycle

    async def __aenter__(self) -> GrblSimController:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.stop()

    async def start(self) -> None:
        """Create the pty and symlink and start the board's main loop."""
        if self._task is not None:
            return
        self._wake = asyncio.Event()
        self._changed = asyncio.Event()
        self._port = PtyPort(PORT, self.path, self)
        self._port.plug()
        self._task = asyncio.get_running_loop().create_task(self._run(), name=f"grbl {self.path}")
        log.info("grbl sim started", path=self.path, flavour=self.config.flavour)

    async def stop(self) -> None:
        """Stop the board, close the pty and remove the symlink."""
        if self._closed:
            return
        self._closed = True
        self._cancel_open_timer()
        result: BaseException | None = None
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                try:
                    await self._task
                except Exception as exc:
                    result = exc
        if self._port is not None:
            self._port.unplug()
        if result is not None:
            raise RuntimeError("the simulated grbl board crashed") from result

    close = stop

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

    async def wait_for(self, predicate: Callable[[], bool], timeout: float = 5.0) -> None:
        """Return once `predicate()` is true; re-checked after every board event."""
        try:
            async with asyncio.timeout(timeout):
                while not predicate():
                    self._check_running()
                    assert self._changed is not None
                    await self._changed.wait()
        except TimeoutError:
            name = getattr(predicate, "__qualname__", repr(predicate))
            raise TimeoutError(
                f"simulated grbl: {name} still false after {timeout} s (state {self.state})"
            ) from None

    async def wait_state(self, state: str, timeout: float = 5.0) -> None:
        await self.wait_for(lambda: self.state == state, timeout)

    async def wait_attached(self, timeout: float = 5.0) -> None:
        await self.wait_for(lambda: self._attached and not self._open_pending, timeout)

    def _check_running(self) -> None:
        task = self._task
        if task is None:
            raise RuntimeError("the simulated grbl board is not started")
        if task.done() and not task.cancelled() and task.exception() is not None:
            raise RuntimeError("the simulated grbl board crashed") from task.exception()

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

    def inject_garbage(self, data: bytes) -> None:
        """Write `data` raw to the host, as a noisy or broken board might."""
        if self._port is not None and self._port.write(data):
            self._keep(self.sent, Received(time.monotonic(), PORT, data, "raw"))
            self._pulse()

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
        if self._open_pending:
            return  # the board is still in its bootloader
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
        if port is None or not self._attached or self._open_pending:
            return  # a board with nobody listening talks to nobody
        data = line.encode("latin-1", "replace")
        if port.write(data + EOL):
            self._keep(self.sent, Received(time.monotonic(), PORT, data, "line"))

    def _keep(self, history: list[Received], entry: Received) -> None:
        history.append(entry)
        limit = self.config.history
        if limit is not None and len(history) > 2 * limit:
            del history[:-limit]

    def _kick(self) -> None:
        if self._wake is not None:
            self._wake.set()
        self._pulse()

    def _pulse(self) -> None:
        if self._changed is not None:
            self._changed.set()
            self._changed = asyncio.Event()

    async def _run(self) -> None:
        try:
            await self._loop()
        except Exception:
            log.exception("grbl sim crashed", path=self.path)
            self._pulse()
            raise

    async def _loop(self) -> None:
        assert self._wake is not None
        board = self._board
        while True:
            self._wake.clear()
            steps = 0
            while steps < MAX_STEPS and board.tick():
                steps += 1
            if steps:
                self._pulse()
            if steps >= MAX_STEPS:
                await asyncio.sleep(0)
                continue
            deadline = board.next_deadline()
            if deadline is None:
                await self._wake.wait()
                continue
            delay = max(deadline - time.monotonic(), 0.0005)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(delay):
                    await self._wake.wait()
