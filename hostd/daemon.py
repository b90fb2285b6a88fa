"""The daemon's core: the state directory, the job store, and every configured machine.

The composition root: it builds the layers and runs each machine as its own
task, so that one machine's unplug, alarm or slow board never waits on
another's. Machines with `data_port = "sim"` get a simulated board on a
pseudo-terminal pair under `state_dir/sim/`, opened like any serial port: the
board its dialect's registry entry names (`simulator`), imported only then.

`[daemon]`, the section of the config file this module reads, is declared
here (`DaemonConfig`); hostd/config.py assembles the whole file.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Awaitable, Callable, Sequence
from pathlib import Path
from typing import Annotated, Any, Literal, Protocol, cast

import structlog
from pydantic import BaseModel, ConfigDict, Field

from hostd.machine import preflight
from hostd.machine.config import MachineConfig
from hostd.machine.jobstore import JobStore
from hostd.machine.machine import Machine
from hostd.machine.workers import WorkerPool
from hostd.protocol.dialects import load_simulator

log = structlog.get_logger(__name__)

DB_NAME = "hostd.db"
SIM_SPEED = 10.0  # simulated boards move ten times faster than real ones
SIM_HISTORY = 1000  # lines a simulated board remembers: a daemon runs for days


class DaemonConfig(BaseModel):
    """`[daemon]`: the socket, the state directory, the limits of clients and workers."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    socket: str = "/run/hostd/hostd.sock"
    state_dir: str = "/var/lib/hostd"
    # Members of this group may use the socket (it is created 0660 with this
    # group); root and the daemon's own user always may. None: nobody else.
    group: str | None = None
    log_level: Literal["debug", "info", "warning", "error"] = "info"
    # Clients connected at once; one more is told the daemon is full and closed.
    max_clients: Annotated[int, Field(ge=1, le=10_000)] = 128
    # Seconds a client may leave a request line half-sent before it is disconnected
    # (a client quiet between lines stays connected however long).
    line_timeout: Annotated[float, Field(gt=0, le=3600)] = 10.0
    # Bytes the jobs directory may hold, published files and unfinished
    # uploads together; an upload that would pass it is refused (1009). None: no limit.
    jobs_quota: Annotated[int, Field(gt=0)] | None = None
    # Seconds an unfinished upload may go without a chunk before it is removed.
    upload_expiry: Annotated[float, Field(gt=0)] = 3600.0
    # The event loop the daemon runs on: uvloop, or asyncio's own (docs/performance.md
    # has the figures behind the default; the test suite runs on the default).
    event_loop: Literal["asyncio", "uvloop"] = "uvloop"
    # Reading a whole G-code file (file.analyze, job.recovery, job.start's checks) runs
    # on worker processes (hostd/machine/workers.py), each file within these limits:
    # seconds, and bytes of address space per worker (docs/gcode.md). Past one: 1013.
    analysis_timeout: Annotated[float, Field(gt=0, le=3600)] = 600.0
    analysis_memory: Annotated[int, Field(ge=64 << 20)] = 1 << 30
    # Start one worker as the daemon starts, so that the first job.start or file.analyze
    # does not wait a second or more for a new interpreter (docs/performance.md).
    prewarm_workers: bool = True
    # Added to the analysis workers' niceness, so that on a small machine the daemon's own
    # loop (feedholds, the job's lines) goes first. The test suite sets 0: its own six
    # processes keep two cores busy, and a niced worker there waits tens of seconds.
    analysis_nice: Annotated[int, Field(ge=0, le=19)] = 10


class Settings(Protocol):
    """What the daemon reads of the config (hostd/config.py's `Config` is one)."""

    @property
    def daemon(self) -> DaemonConfig: ...
    @property
    def machines(self) -> Sequence[MachineConfig]: ...


class SimBoard(Protocol):
    """A simulated board, as the daemon runs it (hostd/sim, by a dialect's factory)."""

    async def start(self) -> None: ...
    async def close(self) -> None: ...


class Daemon:
    def __init__(self, config: Settings) -> None:
        self.config = config
        self.state_dir = Path(config.daemon.state_dir)
        self.jobs_dir = self.state_dir / "jobs"
        self.machines: dict[str, Machine] = {}
        self.store: JobStore | None = None
        # The simulated boards, by machine id; each of its dialect's own class.
        self.sims: dict[str, Any] = {}
        self._stop = asyncio.Event()
        # Whole-file reading, off this interpreter; its workers start on first use.
        self.workers = WorkerPool(
            timeout=config.daemon.analysis_timeout,
            memory=config.daemon.analysis_memory,
            nice=config.daemon.analysis_nice,
        )

    def machine(self, machine_id: str) -> Machine | None:
        return self.machines.get(machine_id)

    def stop(self) -> None:
        self._stop.set()

    async def run(self, ready: Callable[[], Awaitable[None]] | None = None) -> None:
        """Serve every machine until `stop()`; `ready` is awaited once all are set up."""
        await asyncio.to_thread(self._make_dirs)
        self.store = await asyncio.to_thread(JobStore, self.state_dir / DB_NAME)
        try:
            recovered = await self.store.recover()
            for machine_config in self.config.machines:
                effective = await self._plug_in(machine_config)
                self.machines[effective.id] = Machine(effective, self.store, self.jobs_dir)
            for job in recovered:
                log.warning("job interrupted by a daemon stop", job=job.id, machine=job.machine)
                machine = self.machines.get(job.machine)
                if machine is not None:  # what its board does now is looked at as it connects
                    why = f"job {job.id} was under way when the daemon stopped"
                    machine.ran_unwatched(why, job.id if job.kind == "make" else None)
            async with asyncio.TaskGroup() as tg:
                tasks = [
                    tg.create_task(m.serve(), name=f"machine-{m.id}")
                    for m in self.machines.values()
                ]
                if self.config.daemon.prewarm_workers:
                    # The first analysis then finds its worker started (it never raises).
                    warm = self.workers.prewarm(preflight.__name__)
                    tasks.append(tg.create_task(warm, name="prewarm"))
                if ready is not None:
                    await ready()
                await self._stop.wait()
                # A job still running is stopped on its board before the ports close: left
                # alone, the board would run the lines it holds unwatched, then stand with
                # its spindle or beam on (docs/operations.md, "When the daemon stops").
                await asyncio.gather(*(m.stop_for_shutdown() for m in self.machines.values()))
                for task in tasks:
                    task.cancel()
        finally:
            self.workers.close()
            for sim in self.sims.values():
                with contextlib.suppress(Exception):
                    await sim.close()
            self.store.close()

    def _make_dirs(self) -> None:
        for path in (self.state_dir, self.jobs_dir):
            path.mkdir(mode=0o750, parents=True, exist_ok=True)

    async def _plug_in(self, config: MachineConfig) -> MachineConfig:
        """A simulated machine's ports are real ptys; its config points at them."""
        if not config.simulated:
            return config
        sim_dir = self.state_dir / "sim"
        await asyncio.to_thread(sim_dir.mkdir, mode=0o750, exist_ok=True)
        data = str(sim_dir / f"{config.id}-data")
        control = str(sim_dir / f"{config.id}-control") if config.control_port else None
        factory = load_simulator(config.spec)
        sim = cast(SimBoard, factory(data, control, SIM_SPEED, SIM_HISTORY))
        await sim.start()
        self.sims[config.id] = sim
        return config.model_copy(update={"data_port": data, "control_port": control})
