"""`SimShell`: the asyncio shell that both simulated boards run in.

A simulated board is a pure model that is ticked (hostd/sim/board.py,
hostd/sim/grbl/board.py) and a controller that moves bytes between its ptys
and the model, and time through it. The part of that controller that does
not depend on the firmware lives here: the board's main loop as one owned
task (tick up to MAX_STEPS, then sleep until the next deadline or until
something happens), the lifecycle around it, the events that wake the loop
and the test's waiters, and the kept history of what crossed the ports.

What is the firmware's own stays in its controller, behind the hooks below:
which ports it has and how it plugs them, how it shuts down, whether its
loop can be halted (a hung or resetting g2core), and how much each port may
read (g2core's RX budget; grbl takes every byte into its ring).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from types import TracebackType
from typing import ClassVar, Generic, Protocol, Self, TypeVar

from hostd.sim.config import Received

MAX_STEPS = 512  # board steps per loop iteration before yielding to I/O
MIN_SLEEP = 0.0005  # s the loop sleeps at least when a deadline is already due


class Ticking(Protocol):
    """What the main loop needs of a board model."""

    def tick(self) -> bool: ...  # do one thing that is due; False when nothing is
    def next_deadline(self) -> float | None: ...  # None: nothing to do until new input


BoardT = TypeVar("BoardT", bound=Ticking)
StateT = TypeVar("StateT")


class SimShell(ABC, Generic[BoardT, StateT]):
    """The main-loop task, lifecycle, waiting and history of a simulated board.

    A subclass builds `_board` and its ports in `__init__` / `_plug_ports`, is
    the ports' listener, and calls `_kick()` whenever something happened that
    the loop or a waiter should look at (`_pulse()` wakes only the waiters).
    """

    # How errors name the board: "the {what} crashed", "{name}: ... still false".
    _what: ClassVar[str]
    _name: ClassVar[str]
    _board: BoardT

    def __init__(self, history: int | None) -> None:
        self.received: list[Received] = []
        self.sent: list[Received] = []
        self._history = history  # entries kept in `received` / `sent`; None keeps all
        self._wake: asyncio.Event | None = None  # the main loop should look again
        self._changed: asyncio.Event | None = None  # set and replaced on every board event
        self._main_task: asyncio.Task[None] | None = None
        self._closed = False

    # --- lifecycle

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    async def start(self) -> None:
        """Create the ptys and symlinks and start the board's main loop."""
        if self._main_task is not None:
            return
        self._wake = asyncio.Event()
        self._changed = asyncio.Event()
        self._plug_ports()
        self._main_task = asyncio.get_running_loop().create_task(
            self._run(), name=self._task_name()
        )
        self._log_started()

    async def close(self) -> None:
        """Stop the board, close its ptys and remove the symlinks; raises if it crashed."""
        if self._closed:
            return
        self._closed = True
        crash = await self._shut_down()
        if crash is not None:
            raise RuntimeError(f"the {self._what} crashed") from crash

    # --- what the firmware's controller says

    @property
    @abstractmethod
    def state(self) -> StateT:
        """The board's state, as `wait_state` compares it."""

    @abstractmethod
    def _plug_ports(self) -> None:
        """Create the ports and plug them in (from `start`, before the loop runs)."""

    @abstractmethod
    def _task_name(self) -> str: ...

    @abstractmethod
    def _log_started(self) -> None: ...

    @abstractmethod
    def _log_crash(self) -> None:
        """Log the main loop's crash; called inside the `except`, so with its traceback."""

    @abstractmethod
    async def _shut_down(self) -> Exception | None:
        """End the tasks and unplug the ports (once, from `close`); return a crash."""

    @abstractmethod
    def _situation(self) -> str:
        """What a timed-out `wait_for` reports in brackets after the predicate."""

    @abstractmethod
    def _halted(self) -> bool:
        """Whether the loop must neither tick nor wake for deadlines now."""

    @abstractmethod
    def _read_waiting(self) -> None:
        """Take what the host has written to each port and the port has not read yet
        (`PtyPort.read_waiting`): called before every round of ticks."""

    @abstractmethod
    def _update_reading(self) -> None:
        """Re-plan how much each port may read; called on every kick and after ticking."""

    # --- waiting, without sleeping

    async def wait_for(self, predicate: Callable[[], bool], timeout: float = 5.0) -> None:
        """Return once `predicate()` is true; it is re-checked after every board event."""
        try:
            async with asyncio.timeout(timeout):
                while not predicate():
                    self._check_running()
                    assert self._changed is not None
                    await self._changed.wait()
        except TimeoutError:
            name = getattr(predicate, "__qualname__", repr(predicate))
            raise TimeoutError(
                f"{self._name}: {name} still false after {timeout} s ({self._situation()})"
            ) from None

    async def wait_state(self, state: StateT, timeout: float = 5.0) -> None:
        await self.wait_for(lambda: self.state == state, timeout)

    def _check_running(self) -> None:
        task = self._main_task
        if task is None:
            raise RuntimeError(f"the {self._what} is not started")
        if task.done() and not task.cancelled() and task.exception() is not None:
            raise RuntimeError(f"the {self._what} crashed") from task.exception()

    # --- internals

    def _keep(self, history: list[Received], entry: Received) -> None:
        """Append; past twice `history` entries, drop all but the last `history`."""
        history.append(entry)
        limit = self._history
        if limit is not None and len(history) > 2 * limit:
            del history[:-limit]

    def _kick(self) -> None:
        """Something happened: let the main loop look, re-plan reading, wake waiters."""
        if self._wake is not None:
            self._wake.set()
        self._update_reading()
        self._pulse()

    def _pulse(self) -> None:
        if self._changed is not None:
            self._changed.set()
            self._changed = asyncio.Event()

    async def _run(self) -> None:
        """The board's main loop; a crash is logged and wakes every waiter."""
        try:
            await self._loop()
        except Exception:
            self._log_crash()
            self._pulse()
            raise

    async def _loop(self) -> None:
        """Tick while there is work, then sleep until the next deadline or new input."""
        assert self._wake is not None
        board = self._board
        while True:
            self._wake.clear()
            steps = 0
            halted = self._halted()
            if not halted:
                self._read_waiting()  # as a receive interrupt would have, by now
                while steps < MAX_STEPS and board.tick():
                    steps += 1
            if steps:
                self._update_reading()
                self._pulse()
            if steps >= MAX_STEPS:
                await asyncio.sleep(0)  # let the ports in
                continue
            deadline = None if halted else board.next_deadline()
            if deadline is None:
                await self._wake.wait()
                continue
            # A due deadline means work for the next round; never spin on one.
            delay = max(deadline - time.monotonic(), MIN_SLEEP)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(delay):
                    await self._wake.wait()
