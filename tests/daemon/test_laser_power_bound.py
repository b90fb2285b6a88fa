"""A laser's power from the API never passes the machine's `laser_test_max` (docs/api.md
machine.laser_test and machine.frame, operations.py): a test-fire or a frame asking for
more is refused (-32602, naming the setting) and the beam never comes on, by however
little the ask is over; at the bound itself the test-fire is taken."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest
import pytest_asyncio

from tests.daemon.conftest import GRBL, Rpc, Running, running_daemon
from tests.daemon.test_api import fails
from tests.daemon.test_power import BOXED, grbl_board

pytestmark = pytest.mark.asyncio

MOST = 10.0  # the default laser_test_max


@pytest_asyncio.fixture
async def laser(tmp_path: Path) -> AsyncIterator[tuple[Running, Rpc]]:
    per_machine = [{}, {"dialect": "grbl", "laser": True}]
    async with running_daemon(tmp_path, machines=2, per_machine=per_machine) as d:
        rpc = await d.client()
        await d.idle(rpc, GRBL)
        yield d, rpc
        await rpc.close()


async def test_power_past_laser_test_max_is_refused_and_fires_nothing(
    laser: tuple[Running, Rpc],
) -> None:
    hostd, rpc = laser
    board = grbl_board(hostd)
    (hostd.jobs / "boxed.gcode").write_text(BOXED)
    for power in (MOST + 0.5, MOST * 1.4):
        test = rpc.call("machine.laser_test", machine=GRBL, power=power, duration_s=0.1)
        assert "laser_test_max" in (await fails(-32602, test)).message
        frame = rpc.call("machine.frame", machine=GRBL, file="boxed.gcode", power=power)
        assert "laser_test_max" in (await fails(-32602, frame)).message
    assert all(p == 0 for _, p in board.beam), board.beam
    assert await rpc.call("job.list", machine=GRBL) == []
    await rpc.call("machine.laser_test", machine=GRBL, power=MOST, duration_s=0.1)
    assert any(p > 0 for _, p in board.beam)
