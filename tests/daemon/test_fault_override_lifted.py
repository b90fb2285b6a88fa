"""An override lifted while its fault is still active makes the fault block again at once
(behaviour.md "Faults", docs/api.md fault.override): a job that ran only because of the
override stops with 1007, as it would had the fault come up mid-job, through a real
daemon and socket, the fault's signal from the sim."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest
import pytest_asyncio

from hostd.protocol.states import MachineState
from tests.daemon.conftest import Rpc, Running, running_daemon
from tests.daemon.test_faults import LONG, SIGNALS, fault_became

pytestmark = pytest.mark.asyncio


@pytest_asyncio.fixture
async def laser(tmp_path: Path) -> AsyncIterator[tuple[Running, Rpc]]:
    async with running_daemon(tmp_path, signals=SIGNALS) as hostd:
        rpc = await hostd.client()
        await hostd.idle(rpc)
        await rpc.call("subscribe", topics=["fault", "job"], machine="sim1")
        hostd.daemon.sims["sim1"].set_analog(1, 3.0)  # coolant flowing
        yield hostd, rpc
        await rpc.close()


async def test_lifting_an_override_mid_job_stops_the_job_with_1007(
    laser: tuple[Running, Rpc],
) -> None:
    hostd, rpc = laser
    sim = hostd.daemon.sims["sim1"]
    sim.set_analog(2, 35.0)  # coolant too hot
    await fault_became(rpc, "water_temp", True)
    await rpc.call("fault.override", machine="sim1", fault="water_temp", override=True)
    await rpc.call("file.upload", name="long.gcode", data=LONG)
    job_id = (await rpc.call("job.start", machine="sim1", file="long.gcode"))["job"]
    await sim.wait_state(MachineState.RUN)
    lifted = await rpc.call("fault.override", machine="sim1", fault="water_temp", override=False)
    assert lifted["active"] and not lifted["overridden"]
    note = await rpc.notification(
        lambda n: (
            n["method"] == "job"
            and n["params"]["job"]["id"] == job_id
            and n["params"]["job"]["state"] not in ("running", "paused")
        )
    )
    job = note["params"]["job"]
    assert job["state"] == "failed", job
    assert job["error"]["code"] == 1007 and "water_temp" in job["error"]["message"]
    assert job["lines_acked"] < job["lines_total"]
