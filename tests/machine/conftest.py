"""An engine, or a whole machine with its job store, on the simulated board over a real pty."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import pytest_asyncio

from hostd.config import MachineConfig
from hostd.machine.engine import Engine
from hostd.machine.events import (
    Console,
    EngineEvent,
    Event,
    ExceptionRaised,
    JobChanged,
    StatusChanged,
    SupervisorChanged,
)
from hostd.machine.jobstore import Job, JobStore
from hostd.machine.machine import Machine
from hostd.machine.stream import JobStream
from hostd.machine.supervisor import State as Sup
from hostd.protocol.program import program_lines
from hostd.sim import SimConfig, SimController

FAST = SimConfig(
    speed_factor=50.0,
    status_interval=0.02,
    feedhold_decel=0.02,
    boot_time=0.02,
    planner_depth=48,  # g2core's: a job is not starved by a passing stall of the test machine
)


def long_moves(count: int, feed: int = 1500) -> list[str]:
    """`count` job lines of 40 mm each, for a job that must complete: ~32 ms a line on
    FAST's board (1.6 s in real time at F1500). The engine keeps `window` (4) lines on the
    board, so the board runs dry only if the host is ~0.1 s late to refill; shorter moves
    (a millisecond on FAST) underflow, by design a job fault, on a loaded test machine."""
    return [f"G1 X{(i % 2) * 40} Y{i % 9} F{feed}" for i in range(count)]


@dataclass
class Recorder:
    """Every event an engine told (a rig's) or a machine published (a bench's), in order."""

    events: list[Event | EngineEvent] = field(default_factory=list)
    _arrived: asyncio.Event = field(default_factory=asyncio.Event)

    def __call__(self, event: Event | EngineEvent) -> None:
        self.events.append(event)
        self._arrived.set()

    async def wait_for(
        self, predicate: Callable[[Event | EngineEvent], bool], timeout: float = 5.0
    ) -> Event | EngineEvent:
        """The first event, past or future, that satisfies the predicate.

        `timeout` bounds a wait that would otherwise hang; it is no timing check.
        """
        seen = 0
        async with asyncio.timeout(timeout):
            while True:
                for event in self.events[seen:]:
                    if predicate(event):
                        return event
                seen = len(self.events)
                self._arrived.clear()
                await self._arrived.wait()

    def tx(self) -> list[str]:
        return [e.text for e in self.events if isinstance(e, Console) and e.direction == "tx"]

    def index_of(self, predicate: Callable[[Event | EngineEvent], bool]) -> int:
        return next(i for i, e in enumerate(self.events) if predicate(e))

    def lockout_read_at(self) -> int:
        """Where the engine first read that the board locked out."""

        def locked(e: Event | EngineEvent) -> bool:
            if isinstance(e, ExceptionRaised):
                return True
            return isinstance(e, StatusChanged) and e.report.get("stat") in (2, 12, 13)

        return self.index_of(locked)

    def max_in_flight(self) -> int:
        """Unanswered lines at the worst moment, counted from the engine's own traffic."""
        out = worst = 0
        for e in self.events:
            if not isinstance(e, Console):
                continue
            if e.direction == "tx" and len(e.text) > 1:  # realtime bytes take no slot
                out += 1
                worst = max(worst, out)
            elif (
                e.direction == "rx"
                and e.text.startswith('{"r":')
                and '"SYSTEM READY"' not in e.text
            ):
                out -= 1
        return worst


@dataclass
class Rig:
    sim: SimController
    engine: Engine
    recorder: Recorder

    def job(self, lines: Iterable[str]) -> JobStream:
        stream = JobStream(program_lines(lines))
        self.engine.start_stream(stream)
        return stream

    def received_lines(self) -> list[bytes]:
        return [r.data for r in self.sim.received if r.kind == "line"]


@contextlib.asynccontextmanager
async def running(engine: Engine) -> AsyncIterator[asyncio.Task[None]]:
    task = asyncio.create_task(engine.serve())
    try:
        yield task
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


def machine_config(path: str, control: str | None = None, **overrides: object) -> MachineConfig:
    values: dict[str, object] = {
        "id": "m1",
        "data_port": path,
        "control_port": control,
        "window": 4,
        "auto_connect": False,
        "heartbeat": 1.0,
        # The daemon's default: a bound against a board that never answers, which no test
        # here waits out (2 s ran out mid-handshake at load average 17 on two cores).
        "handshake_timeout": 5.0,
        "status_interval": 0.1,
    }
    values.update(overrides)
    if values.get("dialect", "g2core") != "g2core":
        del values["window"]  # g2core's own key (its registry entry's options)
    return MachineConfig.model_validate(values)


@pytest_asyncio.fixture
async def rig(tmp_path: Path) -> AsyncIterator[Rig]:
    path = str(tmp_path / "ttyG2")
    async with SimController(path, config=FAST) as sim:
        recorder = Recorder()
        engine = Engine(machine_config(path), recorder)
        engine.console = True  # the recorder reads the traffic
        async with running(engine):
            await engine.connect()
            yield Rig(sim, engine, recorder)


@dataclass
class Bench:
    sim: SimController
    machine: Machine
    store: JobStore
    recorder: Recorder
    jobs: Path

    def write(self, name: str, text: str) -> None:
        (self.jobs / name).write_text(text)

    async def job_ended(self, job_id: int) -> Job:
        def ended(e: Event | EngineEvent) -> bool:
            if not isinstance(e, JobChanged) or e.job["id"] != job_id:
                return False
            return e.job["state"] not in ("running", "paused")

        # A whole job: thousands of lines take longer than one event on a loaded machine.
        await self.recorder.wait_for(ended, timeout=45)
        row = await self.store.get(job_id)
        assert row is not None
        return row

    async def supervisor(self, state: Sup) -> None:
        """Until the supervisor is in `state` (re-checked on each transition published)."""
        if self.machine.supervisor.state is not state:
            await self.recorder.wait_for(
                lambda e: (
                    isinstance(e, SupervisorChanged)
                    and e.target == state.value
                    and self.machine.supervisor.state is state
                )
            )

    def transitions(self) -> list[tuple[str, str, str]]:
        return [
            (e.source, e.event, e.target)
            for e in self.recorder.events
            if isinstance(e, SupervisorChanged)
        ]


@contextlib.asynccontextmanager
async def bench_for(
    tmp_path: Path, name: str = "m1", sim_config: SimConfig = FAST, **overrides: object
) -> AsyncIterator[Bench]:
    path = str(tmp_path / f"tty-{name}")
    jobs = tmp_path / "jobs"
    jobs.mkdir(exist_ok=True)
    store = JobStore(tmp_path / f"{name}.db")
    async with SimController(path, config=sim_config) as sim:
        machine = Machine(machine_config(path, id=name, **overrides), store, jobs)
        recorder = Recorder()
        machine.hub.subscribe(recorder)
        task = asyncio.create_task(machine.serve())
        try:
            await machine.connect()
            bench = Bench(sim, machine, store, recorder, jobs)
            await bench.supervisor(Sup.IDLE)
            yield bench
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
            store.close()


@pytest_asyncio.fixture
async def bench(tmp_path: Path) -> AsyncIterator[Bench]:
    async with bench_for(tmp_path) as b:
        yield b
