"""The daemon's core: the state directory, the job store, and every configured machine.

The composition root: it builds the layers and runs each machine as its own
task, so that one machine's unplug, alarm or slow board never waits on
another's. Machines with `data_port = "sim"` get a simulated board on a
pseudo-terminal pair under `state_dir/sim/`, opened like any serial port.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Awaitable, Callable
from pathlib import Path

import structlog

from hostd.config import Config, MachineConfig
from hostd.machine import preflight
from hostd.machine.jobstore import JobStore
from hostd.machine.machine import Machine
from hostd.machine.workers import WorkerPool
from hostd.sim import SimConfig, SimController
from hostd.sim.grbl import GrblConfig, GrblSimController

log = structlog.get_logger(__name__)

DB_NAME = "hostd.db"
SIM_SPEED = 10.0  # simulated boards move ten times faster than real ones
SIM_PLANNER = 48  # g2core's planner buffers (PLANNER_QUEUE_SIZE)
SIM_HISTORY = 1000  # lines a simulated board remembers: a daemon runs for days


class Daemon:
    def __init__(self, config: Config) -> None:
        self.config = config
        self.state_dir = Path(config.daemon.state_dir)
        self.jobs_dir = self.state_dir / "jobs"
        self.machines: dict[str, Machine] = {}
        self.store: JobStore | None = None
        self.sims: dict[
            str, SimController | GrblSimController
        ] = {}  # the simulated boards, by machine id
        self._stop = asyncio.Event()
        # Whole-file reading, off this interpreter; its workers start on first use.
        self.workers = WorkerPool(
            timeout=config.daemon.analysis_timeout, memory=config.daemon.analysis_memory
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
            for job in await self.store.recover():
                log.warning("job interrupted by a daemon stop", job=job.id, machine=job.machine)
            for machine_config in self.config.machines:
                effective = await self._plug_in(machine_config)
                self.machines[effective.id] = Machine(effective, self.store, self.jobs_dir)
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
        sim: SimController | GrblSimController
        if config.dialect == "grbl":
            # grbl 1.1h as most lasers run it, laser mode on ($32=1).
            grbl = GrblConfig(speed_factor=SIM_SPEED, laser_mode=True, history=SIM_HISTORY)
            sim = GrblSimController(data, grbl)
        else:
            board = SimConfig(
                speed_factor=SIM_SPEED, planner_depth=SIM_PLANNER, history=SIM_HISTORY
            )
            sim = SimController(data, control_path=control, config=board)
        await sim.start()
        self.sims[config.id] = sim
        return config.model_copy(update={"data_port": data, "control_port": control})
