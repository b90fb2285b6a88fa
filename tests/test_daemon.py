"""The daemon's core with a simulated machine: state directory, job history, start and stop."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest

from hostd.config import parse_config
from hostd.daemon import Daemon
from hostd.machine.supervisor import State as Sup

pytestmark = pytest.mark.asyncio


def _setter(event: asyncio.Event) -> Callable[[], Awaitable[None]]:
    async def ready() -> None:
        event.set()

    return ready


def config_for(tmp_path: Path) -> dict[str, object]:
    return {
        "daemon": {"socket": str(tmp_path / "hostd.sock"), "state_dir": str(tmp_path / "state")},
        "machines": [{"id": "sim1", "data_port": "sim", "status_interval": 0.1}],
    }


async def test_a_simulated_machine_connects_streams_and_is_remembered(tmp_path: Path) -> None:
    config = parse_config(config_for(tmp_path))
    daemon = Daemon(config)
    ready = asyncio.Event()
    runner = asyncio.create_task(daemon.run(_setter(ready)))
    async with asyncio.timeout(10):
        await ready.wait()
        machine = daemon.machine("sim1")
        assert machine is not None
        await machine.connect()
        await machine.engine.wait_for(lambda: machine.supervisor.state is Sup.IDLE)
        (daemon.jobs_dir / "square.gcode").write_text("G21\nG1 X5 F6000\nG1 Y5\nG1 X0\nG1 Y0\n")
        job = await machine.start_make("square.gcode")
        await machine.engine.wait_for(lambda: machine.supervisor.state is Sup.IDLE)
        daemon.stop()
        await runner
    assert (tmp_path / "state" / "hostd.db").is_file()

    again = Daemon(config)
    ready = asyncio.Event()
    runner = asyncio.create_task(again.run(_setter(ready)))
    async with asyncio.timeout(10):
        await ready.wait()
        assert again.store is not None
        row = await again.store.get(job.id)
        again.stop()
        await runner
    assert row is not None and row.state == "completed" and row.lines_acked == 5
