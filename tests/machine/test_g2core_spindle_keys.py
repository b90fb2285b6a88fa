"""g2core's spindle, read from the board's own keys on each build, over a real pty.

hostd asks at the handshake which keys the board has (hostd/protocol/g2handshake.py
SPINDLE_KEYS); the simulated board has its build's (hostd/sim/reports.py).
`machine.spindle` then shows in the snapshot the operator sees.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from hostd.machine import operations
from tests.machine.conftest import FAST, bench_for

pytestmark = pytest.mark.asyncio


@pytest.mark.parametrize("fb", [100.26, 101.03, 101.06])
async def test_the_snapshot_shows_the_spindle_the_board_runs(tmp_path: Path, fb: float) -> None:
    async with bench_for(tmp_path, sim_config=replace(FAST, fb=fb)) as bench:
        machine = bench.machine
        engine = machine.engine
        assert engine.model.snapshot()["spindle"] == {"state": "off", "speed": 0.0}
        await operations.spindle(machine, "ccw", 9000)
        await engine.wait_for(lambda: (engine.model.spindle or {}).get("state") == "ccw")
        assert engine.model.snapshot()["spindle"] == {"state": "ccw", "speed": 9000.0}
        await operations.spindle(machine, "cw", None)
        await engine.wait_for(lambda: (engine.model.spindle or {}).get("state") == "cw")
        await operations.spindle(machine, "off", None)
        await engine.wait_for(lambda: (engine.model.spindle or {}).get("state") == "off")
