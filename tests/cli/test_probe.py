"""`hostd probe`, run as a user runs it, against a daemon whose boards have a touch plate.

The daemon runs in the test's own event loop (tests/daemon's `running_daemon`)
so the test can lay the plate on each simulated board and touch it to the bit;
the CLI is a real subprocess over the real socket.
"""

from __future__ import annotations

import asyncio
import json
import os
import sys
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
import pytest_asyncio

from hostd.machine import probing
from hostd.sim.probing import TouchPlate
from tests.daemon.conftest import Running, running_daemon

pytestmark = pytest.mark.asyncio

G2, GRBL = "sim1", "sim2"
TOP = -3.0  # machine Z of the plate's top


@pytest_asyncio.fixture
async def hostd(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> AsyncIterator[Running]:
    monkeypatch.setattr(probing, "SETTLE", 0.0)
    per_machine = [{}, {"dialect": "grbl", "status_interval": 1.0}]
    probe = {"plate": 10.0, "feed": 600.0, "max_travel": 10.0, "retract": 2.0}
    async with running_daemon(tmp_path, machines=2, per_machine=per_machine, probe=probe) as d:
        client = await d.client()
        for machine in (G2, GRBL):
            await d.idle(client, machine)
        await client.close()
        yield d


async def cli(hostd: Running, *args: str) -> tuple[int, str, str]:
    env = dict(os.environ, HOSTD_SOCKET=hostd.socket, NO_COLOR="1", COLUMNS="200")
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "hostd",
        *args,
        env=env,
        stdin=asyncio.subprocess.DEVNULL,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    async with asyncio.timeout(30):
        out, err = await proc.communicate()
    assert proc.returncode is not None
    return proc.returncode, out.decode(), err.decode()


@pytest.mark.parametrize("machine", [G2, GRBL])
async def test_probe_says_where_it_touched_and_what_work_z_reads(
    hostd: Running, machine: str
) -> None:
    sim = hostd.daemon.sims[machine]
    sim.touch_plate(TouchPlate(top=TOP))
    sim.touch(reads=2)
    code, out, err = await cli(hostd, "probe", machine)
    assert code == 0, err
    assert "touch the plate to the bit" in err
    assert f"{machine}: probed Z, touched at Z-3.000 (machine); Z zeroed" in out
    assert "z=12" in out  # 2 mm above the 10 mm plate


async def test_probe_xyz_with_json_answers_the_result(hostd: Running) -> None:
    sim = hostd.daemon.sims[G2]
    sim.touch_plate(TouchPlate(top=TOP, x_face=-2.5, y_face=-2.5, tool_radius=1.5))
    sim.touch(reads=2)
    code, out, err = await cli(hostd, "--json", "probe", G2, "--xyz", "--tool-diameter", "3")
    assert code == 0, err
    result = json.loads(out)
    assert result["zeroed"] == ["z", "x", "y"]
    assert result["position"] == pytest.approx({"z": -3.0, "x": -4.0, "y": -4.0})


async def test_probe_without_the_touch_is_refused_and_says_why(hostd: Running) -> None:
    hostd.daemon.sims[GRBL].touch_plate(TouchPlate(top=TOP))
    code, out, err = await cli(hostd, "probe", GRBL, "--wait", "0.3")
    assert code == 1 and out == ""
    assert "not seen working" in err and "1003" in err


async def test_probe_xyz_needs_the_tool_diameter(hostd: Running) -> None:
    code, _, err = await cli(hostd, "probe", G2, "--xyz")
    assert code != 0 and "--tool-diameter" in err
