"""Whole-file work (analysis, resume planning) off the daemon's interpreter.

Reading a G-code file is pure Python and holds the GIL while it runs: in a
thread, a long or hostile file would still starve the event loop, and with
it every `daemon.info`, every feedhold. So it runs in worker processes, each
its own interpreter, and the loop only awaits a future.

Each worker is a `ProcessPoolExecutor` of one process, so that one stuck or
swollen worker can be killed without failing the others' work:

- time: past `timeout` seconds the worker is killed and replaced, and the
  request is answered `AnalysisLimit` (1013);
- memory: the worker's address space is capped (`RLIMIT_AS`, set in its
  initializer); a file that needs more raises MemoryError there, or the
  worker dies, and the request is answered `AnalysisLimit`; the worker is
  replaced either way;
- the workers run at a lower priority (`nice` 10): on a two-core machine the
  daemon's own loop goes first.

Workers start with the forkserver method (never a fork of the daemon's
threads and loop) and are killed when the daemon stops (`close`). The first
worker costs about a second and a half of CPU on a small machine: the
forkserver starts and imports the G-code readers (its preload). The daemon
starts it as soon as it serves (`prewarm`), so that the first `job.start` or
`file.analyze` does not wait for it (docs/performance.md, issue 30); every
later worker (one replacing a worker killed at a limit) is a fork of the
preloaded server, in milliseconds.

A worker's start blocks: `ProcessPoolExecutor.submit` forks it through the
forkserver, waiting for the server's imports the first time, and holds the
executor's lock meanwhile, the lock `shutdown` takes. So the start runs in a
thread of its own, a daemon thread (the interpreter's exit does not join it,
as it joins `asyncio.to_thread`'s), and an executor killed while it starts is
shut down by that thread once `submit` has returned, never by the loop. A
daemon stopped then (SIGTERM, or a failed bind while the prewarm starts) kills
the forkserver, which ends the `submit` at once (docs/testing.md, "Flaky
tests under load"): it does not wait seconds for the server's imports, nor
leave it and a worker behind.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib
import multiprocessing
import os
import resource
import select
import signal
import threading
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from multiprocessing import forkserver
from typing import Any, TypeVar

import structlog

from hostd.protocol.errors import MachineError

log = structlog.get_logger(__name__)

T = TypeVar("T")

# Seconds per file: a million lines take 25 s on an idle two-core machine, and the
# workers run niced, so several times that on a busy one.
DEFAULT_TIMEOUT = 600.0
DEFAULT_MEMORY = 1 << 30  # bytes of address space per worker
DEFAULT_WORKERS = 1  # files analysed at once; more wait their turn
NICE = 10
START_TIMEOUT = 60.0  # seconds for a new worker to start (not counted in a file's limit)


class AnalysisLimit(MachineError):
    """A file's analysis went past the time or memory allowed for it."""

    code = 1013


def _ready(module: str) -> None:
    """Run on a new worker first: its start-up and imports are not counted in a file's time."""
    importlib.import_module(module)


def _limit(memory: int, nice: int, daemon: int) -> None:
    """Worker initializer: cap the address space, yield the CPU to the daemon, and go
    with the daemon (pid `daemon`)."""
    if memory > 0:
        resource.setrlimit(resource.RLIMIT_AS, (memory, memory))
    if nice:
        os.nice(nice)
    _follow(daemon)


def _follow(daemon: int) -> None:
    """Exit this worker when the daemon has exited, however (SIGKILL, a crash).

    Nothing else would tell it: it waits on its call queue, whose both ends it holds,
    and it holds the forkserver's `alive` pipe open, so that server stays too (two
    processes left for good per killed daemon). A pidfd turns readable when the daemon
    exits; a thread waits on it (a daemon thread: a worker stopped as usual does not
    wait for it).
    """
    try:
        pidfd = os.pidfd_open(daemon)
    except ProcessLookupError:
        os._exit(1)  # gone already
    except OSError:
        return  # no pidfd here (Linux before 5.3): the worker is left as it was

    def wait() -> None:
        waiting = select.poll()  # not select(): no FD_SETSIZE limit on the descriptor
        waiting.register(pidfd, select.POLLIN)
        waiting.poll()
        os._exit(1)

    threading.Thread(target=wait, name="hostd-follow-daemon", daemon=True).start()


class WorkerPool:
    """Run a picklable function on worker processes, with a time and memory limit each."""

    def __init__(
        self,
        workers: int = DEFAULT_WORKERS,
        *,
        timeout: float = DEFAULT_TIMEOUT,
        memory: int = DEFAULT_MEMORY,
        nice: int = NICE,
    ) -> None:
        self.workers = workers
        self.timeout = timeout
        self.memory = memory
        self.nice = nice  # added to the workers' niceness: the daemon's loop goes first
        self._idle: list[ProcessPoolExecutor] = []
        self._all: set[ProcessPoolExecutor] = set()
        self._slots: asyncio.Semaphore | None = None
        self._closed = False
        self._warming: asyncio.Task[None] | None = None
        # Executors whose start (`_submit`, in its thread) has not come back to the loop:
        # `_kill` leaves them to it. `_forking`, under `_lock`: those in `submit`, waiting
        # for the forkserver, which `close` kills to end the wait.
        self._starting: set[ProcessPoolExecutor] = set()
        self._forking: set[ProcessPoolExecutor] = set()
        # Held by `close` (on the loop) and by a start's thread, for a few statements or
        # a spawn of the forkserver: never across a wait for a worker.
        self._lock = threading.Lock()

    async def prewarm(self, module: str) -> None:
        """Start one worker (importing `module`) now, for the first request to take.

        Never raises: a worker that cannot start now is started on first use
        instead, as without this.
        """
        if self._closed or self._idle or self._warming is not None:
            return
        self._warming = asyncio.current_task()
        try:
            executor = await self._start(module)
        except Exception as exc:
            if not self._closed:
                log.warning("worker not started ahead of use", error=str(exc))
            return
        finally:
            self._warming = None
        if self._closed:
            self._kill(executor)
        else:
            self._idle.append(executor)
            log.debug("worker started ahead of use")

    async def warmed(self) -> None:
        """Until the worker `prewarm` is starting, if any, is ready (or failed to start)."""
        warming = self._warming
        if warming is not None:
            await asyncio.wait({warming})

    async def run(self, what: str, fn: Callable[..., T], *args: Any) -> T:
        """`fn(*args)` on a worker; AnalysisLimit past the limits. `what` names it to the user.

        Exceptions `fn` raises come back as they are (pickled). Cancelled, the
        worker is killed: nobody waits for its answer any more.
        """
        if self._slots is None:
            self._slots = asyncio.Semaphore(self.workers)
        async with self._slots:
            if not self._idle:
                await self.warmed()  # the worker on its way, if one is, not a second one
            if self._closed:
                raise AnalysisLimit(f"{what}: the daemon is stopping")
            executor = self._idle.pop() if self._idle else await self._start(fn.__module__)
            done = False
            try:
                future = executor.submit(fn, *args)
                result: T = await asyncio.wait_for(asyncio.wrap_future(future), self.timeout)
                done = True
                return result
            except TimeoutError:
                log.warning("analysis over its time limit: worker killed", what=what)
                raise AnalysisLimit(
                    f"{what} took longer than {self.timeout:g} s, the limit for one file",
                    {"limit": "time", "seconds": self.timeout},
                ) from None
            except (MemoryError, BrokenProcessPool):
                log.warning("analysis over its memory limit: worker replaced", what=what)
                raise AnalysisLimit(
                    f"{what} needed more than {self.memory >> 20} MiB, the limit for one file",
                    {"limit": "memory", "bytes": self.memory},
                ) from None
            except Exception:
                done = True  # the function's own error: the worker is fine
                raise
            finally:
                if done and not self._closed:
                    self._idle.append(executor)
                else:
                    self._kill(executor)

    async def _start(self, module: str) -> ProcessPoolExecutor:
        """A new worker, started and ready (its imports done)."""
        context = multiprocessing.get_context("forkserver")
        # The forkserver imports the module once, when it starts (the first worker):
        # every later worker is a fork of it, started in milliseconds, not another
        # second and a half of imports. Set after the server started, it changes nothing.
        context.set_forkserver_preload([module])
        _forget_killed_forkserver()
        executor = ProcessPoolExecutor(
            max_workers=1,
            mp_context=context,
            initializer=_limit,
            initargs=(self.memory, self.nice, os.getpid()),
        )
        self._all.add(executor)
        loop = asyncio.get_running_loop()
        submitted: asyncio.Future[Future[None]] = loop.create_future()
        self._starting.add(executor)
        thread = threading.Thread(
            target=self._submit,
            args=(executor, module, loop, submitted),
            name="hostd-worker-start",
            daemon=True,
        )
        try:
            thread.start()
        except BaseException:
            self._starting.discard(executor)
            self._kill(executor)
            raise
        try:
            async with asyncio.timeout(START_TIMEOUT):
                ready = await submitted
                await asyncio.wrap_future(ready)
        except BaseException:
            self._kill(executor)
            raise
        return executor

    def _submit(
        self,
        executor: ProcessPoolExecutor,
        module: str,
        loop: asyncio.AbstractEventLoop,
        submitted: asyncio.Future[Future[None]],
    ) -> None:
        """In the start's own thread: the first `submit`, which starts the worker process.

        It waits for the forkserver to fork the process (to start, and import, the
        first time) while it holds the executor's lock. Its outcome goes back to the
        loop (`_submitted`); with the loop gone, this thread stops the worker itself.
        """
        outcome: Future[None] | BaseException
        try:
            with self._lock:
                if self._closed:
                    raise AnalysisLimit("the daemon is stopping")
                # The server started here (a spawn, milliseconds: its imports are not
                # waited for), not inside `submit`, and under the lock: `close`, which
                # takes it too, then finds this start in `_forking` with the server's pid
                # known, or finds it not begun (`_closed` then stops it above).
                forkserver.ensure_running()
                self._forking.add(executor)
            try:
                outcome = executor.submit(_ready, module)
            finally:
                with self._lock:
                    self._forking.discard(executor)
        except BaseException as exc:  # handed to the loop, which raises it in `_start`
            outcome = exc
        try:
            loop.call_soon_threadsafe(self._submitted, executor, submitted, outcome)
        except RuntimeError:  # the loop is closed: nobody takes this worker
            _stop(executor)

    def _submitted(
        self,
        executor: ProcessPoolExecutor,
        submitted: asyncio.Future[Future[None]],
        outcome: Future[None] | BaseException,
    ) -> None:
        """On the loop: a start's `submit` came back; its lock is free again."""
        self._starting.discard(executor)
        if executor not in self._all:  # killed while it started (`close`, a cancelled start)
            _stop(executor)
            outcome = AnalysisLimit("the daemon is stopping")
        if submitted.done():  # cancelled, or past START_TIMEOUT: nobody waits
            return
        if isinstance(outcome, BaseException):
            submitted.set_exception(outcome)
        else:
            submitted.set_result(outcome)

    def _kill(self, executor: ProcessPoolExecutor) -> None:
        """Stop a worker now, whatever it is doing; never blocks the loop."""
        if executor not in self._all:
            return  # stopped already
        self._all.discard(executor)
        if executor in self._starting:
            # Its start's thread holds the lock `shutdown` takes: that thread's
            # outcome, back on the loop, stops it (`_submitted`).
            return
        _stop(executor)

    def close(self) -> None:
        """Kill every worker (the daemon stops); later calls are refused."""
        with self._lock:
            self._closed = True
            forking = bool(self._forking)
        if forking:
            # A start waits in `submit` for the forkserver (its imports, the first
            # time): killed, the server answers that wait at once, with an error.
            _kill_forkserver()
        self._idle.clear()
        for executor in list(self._all):
            self._kill(executor)


def _stop(executor: ProcessPoolExecutor) -> None:
    """Kill an executor's process and shut it down: only while no `submit` holds its lock."""
    processes = getattr(executor, "_processes", None) or {}
    for process in list(processes.values()):
        if process.is_alive():
            process.kill()
    executor.shutdown(wait=False, cancel_futures=True)


# Forkservers `_kill_forkserver` killed and reaped, by pid, until `_forget_killed_forkserver`.
_reaped: set[int] = set()


def _kill_forkserver() -> None:
    """Kill the forkserver the workers are forked from, and reap it, so that no start of
    this daemon's gets another one started.

    multiprocessing has no public way to stop it: this reads its pid and takes its lock
    (`ForkServer._forkserver_pid`, `_lock`, private). Under that lock a `submit` on its
    way to the server either reached it (its wait then ends, the pipe closed) or finds
    it reaped (`ensure_running`'s `waitpid` raises ChildProcessError) where, had the
    server only died, it would start another and wait seconds for its imports.
    """
    server: Any = forkserver._forkserver
    with server._lock:
        pid = server._forkserver_pid
        if not isinstance(pid, int) or pid in _reaped:
            return
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
        with contextlib.suppress(ChildProcessError):
            os.waitpid(pid, 0)  # SIGKILL: it is gone in a moment
        _reaped.add(pid)
    log.warning("analysis worker's start stopped: its forkserver killed", pid=pid)


def _forget_killed_forkserver() -> None:
    """Forget a forkserver `_kill_forkserver` reaped, as `ensure_running` forgets one that
    died, so that the next worker starts a new one (a pool closed, another started: tests)."""
    server: Any = forkserver._forkserver
    with server._lock:
        pid = server._forkserver_pid
        if pid not in _reaped:
            return
        _reaped.discard(pid)
        os.close(server._forkserver_alive_fd)
        server._forkserver_address = None
        server._forkserver_alive_fd = None
        server._forkserver_pid = None
