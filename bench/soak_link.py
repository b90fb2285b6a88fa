"""Soak, in one process over real pseudo-terminals: unplug/re-plug and alarms mid-job.

- 100 unplug and re-plug cycles, each mid-job: no crash, the job ends
  `interrupted` with `lines_acked` exactly what the board answered for it,
  the machine reconnects to idle every time, and tasks, file descriptors
  and memory do not grow.
- 50 alarms raised at random points of a stream: not one G-code line
  written after the daemon read the alarm.

Run by `make soak` after bench/soak.py; exit status 1 on any failure.
"""

from __future__ import annotations

import asyncio
import os
import random
import re
import resource
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from hostd.config import MachineConfig
from hostd.logs import configure_logging
from hostd.machine.events import Console, Event, ExceptionRaised, StatusChanged
from hostd.machine.jobstore import JobStore
from hostd.machine.machine import Machine
from hostd.machine.supervisor import State as Sup
from hostd.protocol.states import MachineState
from hostd.sim import SimConfig, SimController

BOARD = SimConfig(speed_factor=50.0, status_interval=0.02, feedhold_decel=0.01,
                  boot_time=0.01, planner_depth=48, history=2000)  # fmt: skip
# A job line's answer: an empty body, or the line's N word echoed (jv 4).
_OK_ANSWER = re.compile(r'\{"r":\{(?:"n":\d+)?\},"f":\[1,0,')
PROGRAM = "".join(f"G1 X{(i % 2) * 10} Y{i % 5} F3000\n" for i in range(400))


class Soak:
    def __init__(self, root: Path) -> None:
        self.root = root
        self.failures: list[str] = []
        self.events: list[Event] = []
        self.changed = asyncio.Event()

    def check(self, ok: bool, what: str) -> None:
        if not ok:
            self.failures.append(what)
            print(f"  FAIL: {what}", flush=True)

    def listen(self, event: Event) -> None:
        self.events.append(event)
        self.changed.set()

    async def until(self, machine: Machine, state: Sup, seconds: float = 10.0) -> None:
        async with asyncio.timeout(seconds):
            while machine.supervisor.state is not state:
                self.changed.clear()
                await self.changed.wait()

    async def job_end(self, machine: Machine, job_id: int) -> str:
        async with asyncio.timeout(10):
            while True:
                job = machine.job
                if job is not None and job.id == job_id and job.state not in ("running", "paused"):
                    return job.state
                self.changed.clear()
                await self.changed.wait()


def fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


async def setup(
    soak: Soak, name: str
) -> tuple[SimController, Machine, JobStore, asyncio.Task[None]]:
    path = str(soak.root / f"tty-{name}")
    jobs = soak.root / "jobs"
    jobs.mkdir(exist_ok=True)
    (jobs / "part.gcode").write_text(PROGRAM)
    sim = SimController(path, config=BOARD)
    await sim.start()
    store = JobStore(soak.root / f"{name}.db")
    config = MachineConfig(id=name, data_port=path, auto_connect=True, heartbeat=1.0)
    machine = Machine(config, store, jobs)
    machine.engine.console = True
    machine.hub.subscribe(soak.listen)
    task = asyncio.create_task(machine.serve())
    await machine.connect()
    await soak.until(machine, Sup.IDLE)
    return sim, machine, store, task


def received_more(sim: SimController, count: int) -> Callable[[], bool]:
    """Whether the board has read more than `count` lines: bound now, not at the call
    (a lambda with a default argument for it is one mypy cannot type)."""
    return lambda: len(sim.received) > count


async def unplug_cycles(soak: Soak, cycles: int) -> None:
    print(f"== unplug and re-plug mid-job, {cycles} cycles", flush=True)
    sim, machine, store, task = await setup(soak, "unplug")
    rng = random.Random(1)
    baseline: tuple[int, int, float] | None = None
    started = time.monotonic()
    for cycle in range(cycles):
        soak.events.clear()
        job = await machine.start_make("part.gcode")
        at = rng.randint(5, 120)
        await sim.wait_for(received_more(sim, at), timeout=10)
        await sim.unplug()
        state = await soak.job_end(machine, job.id)
        row = await store.get(job.id)
        soak.check(state == "interrupted", f"cycle {cycle}: job ended {state}")
        soak.check(row is not None and row.state == "interrupted", f"cycle {cycle}: row {row}")
        if row is not None:
            # Exactly the answers the daemon read (answers still in the pipe when the
            # cable went are lost with it: the board sent them, nobody received them).
            read = sum(
                1
                for e in soak.events
                if isinstance(e, Console) and e.direction == "rx"
                and _OK_ANSWER.match(e.text)
            )  # fmt: skip
            soak.check(
                row.lines_acked == read,
                f"cycle {cycle}: lines_acked {row.lines_acked}, answers read {read}",
            )
            soak.check(row.lines_acked <= row.lines_sent, f"cycle {cycle}: acked over sent")
        await sim.replug()
        await soak.until(machine, Sup.IDLE)
        soak.events.clear()
        if cycle == 4:  # after warm-up: what must not grow from here on
            baseline = (fds(), len(asyncio.all_tasks()), rss_mib())
    assert baseline is not None
    now = (fds(), len(asyncio.all_tasks()), rss_mib())
    took = time.monotonic() - started
    print(f"  {cycles} cycles in {took:.1f} s; fds {baseline[0]} -> {now[0]}, tasks "
          f"{baseline[1]} -> {now[1]}, max RSS {baseline[2]:.1f} -> {now[2]:.1f} MiB",
          flush=True)  # fmt: skip
    soak.check(now[0] <= baseline[0], f"file descriptors grew: {baseline[0]} -> {now[0]}")
    soak.check(now[1] <= baseline[1], f"tasks grew: {baseline[1]} -> {now[1]}")
    soak.check(now[2] - baseline[2] < 8, f"memory grew {now[2] - baseline[2]:.1f} MiB")
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    await sim.close()
    store.close()


async def alarm_points(soak: Soak, count: int) -> None:
    print(f"== alarms at random points of a stream, {count} jobs", flush=True)
    sim, machine, store, task = await setup(soak, "alarm")
    rng = random.Random(2)
    worst = 0
    for n in range(count):
        soak.events.clear()
        job = await machine.start_make("part.gcode")
        at = rng.randint(1, 200)
        await sim.wait_for(received_more(sim, at + 10), timeout=10)
        sim.limit_switch(rng.choice("xyz"))
        state = await soak.job_end(machine, job.id)
        soak.check(state == "failed", f"job {n}: ended {state}")
        read_at = next(
            (i for i, e in enumerate(soak.events) if isinstance(e, ExceptionRaised)
             or (isinstance(e, StatusChanged) and e.report.get("stat") == MachineState.ALARM)),
            None,
        )  # fmt: skip
        soak.check(read_at is not None, f"job {n}: the alarm was never read")
        if read_at is not None:
            after = [
                e.text for e in soak.events[read_at:]
                if isinstance(e, Console) and e.direction == "tx" and e.text.startswith("G")
            ]  # fmt: skip
            worst = max(worst, len(after))
            soak.check(not after, f"job {n}: {len(after)} G-code lines written after the alarm")
        await machine.engine.clear()
        await soak.until(machine, Sup.IDLE)
    print(f"  G-code lines written after an alarm was read: at most {worst}", flush=True)
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    await sim.close()
    store.close()


async def main(cycles: int, alarms: int) -> int:
    configure_logging("error")
    with tempfile.TemporaryDirectory(prefix="hostd-soak-") as tmp:
        soak = Soak(Path(tmp))
        await unplug_cycles(soak, cycles)
        await alarm_points(soak, alarms)
    print(f"\nsoak (link): {'FAIL' if soak.failures else 'PASS'}", flush=True)
    return 1 if soak.failures else 0


if __name__ == "__main__":
    quick = "--quick" in sys.argv
    sys.exit(asyncio.run(main(10 if quick else 100, 5 if quick else 50)))
