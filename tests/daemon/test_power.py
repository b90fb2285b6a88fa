"""Overrides, laser test-fire, frame and macros (issue 29), on both simulated dialects.

A g2core board and a grbl laser, simulated on real ptys, reached through the
real Unix socket. What a user would notice: an override changed mid-job shows
in the snapshot and the board's own settings; the test-fire's beam always ends
off; a frame traces the job's box with the beam off; a macro runs its lines and
no parameter can smuggle another line in.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio

from hostd.sim import SimController
from tests.daemon.conftest import Rpc, Running, running_daemon
from tests.daemon.test_api import fails, job_end

pytestmark = pytest.mark.asyncio

G2, GRBL = "sim1", "sim2"
MACHINES = (G2, GRBL)
# Long enough to be under way when the override is asked (the sims run 10x real speed).
LONG_JOB = "G21 G90\nG1 X0 Y0 F600\n" + "".join(
    f"G1 X{10 + (i % 2) * 10} Y{i % 7} F600\n" for i in range(60)
)


@pytest_asyncio.fixture
async def both(tmp_path: Path) -> AsyncIterator[tuple[Running, Rpc]]:
    async with running_daemon(
        tmp_path, machines=2, per_machine=[{}, {"dialect": "grbl", "laser": True}]
    ) as d:
        client = await d.client()
        await client.call("subscribe", topics=["job", "status"])
        for machine in MACHINES:
            await d.idle(client, machine)
        yield d, client
        await client.close()


def g2_sim(hostd: Running) -> SimController:
    sim = hostd.daemon.sims[G2]
    assert isinstance(sim, SimController)
    return sim


async def overrides_shown(rpc: Rpc, machine: str, want: dict[str, float]) -> None:
    await rpc.notification(
        lambda n: (
            n["method"] == "status"
            and n["params"]["machine"] == machine
            and n["params"]["snapshot"]["overrides"] is not None
            and all(n["params"]["snapshot"]["overrides"].get(k) == v for k, v in want.items())
        )
    )


async def test_g2core_knows_its_overrides_from_the_start(both: tuple[Running, Rpc]) -> None:
    _, rpc = both
    snap = await rpc.call("machine.status", machine=G2)
    assert snap["overrides"] == {"feed": 100.0, "rapid": 100.0, "spindle": 100.0}


@pytest.mark.parametrize("machine", MACHINES)
async def test_an_override_changed_mid_job_shows_in_the_snapshot(
    both: tuple[Running, Rpc], machine: str
) -> None:
    hostd, rpc = both
    (hostd.jobs / "long.gcode").write_text(LONG_JOB)
    job = await rpc.call("job.start", machine=machine, file="long.gcode")
    await rpc.notification(
        lambda n: (
            n["method"] == "status"
            and n["params"]["machine"] == machine
            and n["params"]["snapshot"]["state"]["name"] == "RUN"
        )
    )
    got = await rpc.call("machine.override", machine=machine, feed=150, spindle=80)
    assert got["feed"] == 150 and got["spindle"] == 80
    await overrides_shown(rpc, machine, {"feed": 150, "spindle": 80})
    snap = await rpc.call("machine.status", machine=machine)
    assert snap["job"]["state"] == "running"  # the job went on under the override
    if machine == G2:
        board = g2_sim(hostd)._board.settings
        assert board.override("feed") == pytest.approx(1.5)
        assert board.override("spindle") == pytest.approx(0.8)
    await rpc.call("job.cancel", machine=machine)
    await job_end(rpc, job["job"])


async def test_g2core_refuses_an_override_its_firmware_would_refuse(
    both: tuple[Running, Rpc],
) -> None:
    hostd, rpc = both
    err = await fails(-32602, rpc.call("machine.override", machine=G2, rapid=150))
    assert "5 to 100" in err.message
    assert g2_sim(hostd)._board.settings.override("rapid") == 1.0
    got = await rpc.call("machine.override", machine=G2, rapid=25)
    assert got["rapid"] == 25


async def test_a_program_end_puts_g2cores_feed_override_back(both: tuple[Running, Rpc]) -> None:
    _, rpc = both
    await rpc.call("machine.override", machine=G2, feed=120)
    await rpc.call("machine.send", machine=G2, line="M30")
    await overrides_shown(rpc, G2, {"feed": 100})


def traced(hostd: Running, machine: str) -> list[Any]:
    """The moves the simulated board made (as tests/daemon/test_resume_safety.py reads them)."""
    sim = hostd.daemon.sims[machine]
    record = sim._board.traversed if isinstance(sim, SimController) else sim.board.traversed
    return list(record)
