"""`[web] control = false` (docs/web.md): the dashboard only watches. Every method that is
not a read answers -32601 "watch only" over the WebSocket, with parameters it would
otherwise take, so no watch-only tab can move the machine, fire the laser, start a job,
lift a fault's block or change a file; the reads alone are served."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from tests.web.conftest import running_web

pytestmark = pytest.mark.asyncio

M = {"machine": "sim1"}
# docs/web.md's reads, and macro.list (it lists, never runs).
READS = {
    "rpc.discover",
    "daemon.info",
    "machine.list",
    "machine.status",
    "settings.get",
    "file.list",
    "file.analyze",
    "job.get",
    "job.list",
    "fault.list",
    "macro.list",
    "subscribe",
    "unsubscribe",
}
# Every other method, with parameters it takes: refused for being watch only, not for them.
CONTROL: dict[str, dict[str, Any]] = {
    "machine.connect": M,
    "machine.disconnect": M,
    "machine.send": {**M, "line": "G0 X5"},
    "machine.maintenance": {**M, "line": "$H"},
    "machine.feedhold": M,
    "machine.cycle_start": M,
    "machine.queue_flush": M,
    "machine.job_kill": M,
    "machine.reset": M,
    "machine.clear": M,
    "machine.alarm": M,
    "machine.shutdown": M,
    "machine.jog": {**M, "axes": {"x": 5}, "feed": 600},
    "machine.jog_stop": M,
    "machine.override": {**M, "feed": 150},
    "machine.home": M,
    "machine.zero": {**M, "axes": {"x": 0}},
    "machine.goto_zero": M,
    "machine.spindle": {**M, "state": "cw", "speed": 1000},
    "machine.probe": {**M, "kind": "z", "plate": 10},
    "machine.safety_door": M,
    "machine.laser_test": {**M, "power": 1, "duration_s": 1},
    "machine.frame": {**M, "file": "a.nc"},
    "job.start": {**M, "file": "a.nc"},
    "job.pause": M,
    "job.resume": M,
    "job.cancel": M,
    "job.tool_change_done": M,
    "job.recovery": {**M, "file": "a.nc", "line": 1},
    "fault.override": {**M, "fault": "water_temp", "override": True},
    "fault.clear": {**M, "fault": "serial"},
    "file.upload": {"name": "b.nc", "data": "G0 X1\n"},
    "file.delete": {"name": "a.nc"},
    "macro.run": {**M, "name": "x"},
    "settings.set": {**M, "values": {"x": 1}},
}


async def test_watch_only_refuses_every_method_but_the_reads(tmp_path: Path) -> None:
    async with running_web(tmp_path, control=False) as web:
        rpc = await web.hostd.client()
        try:
            await web.hostd.idle(rpc)
            await rpc.call("file.upload", name="a.nc", data="G0 X1\n")
        finally:
            await rpc.close()
        api = await web.ws()
        try:
            discovered = await api.call("rpc.discover")
            # A method added later is judged here too: a read, or refused.
            assert {m["name"] for m in discovered["methods"]} == READS | set(CONTROL)
            for method, params in CONTROL.items():
                answer = await api.request(method, **params)
                assert "error" in answer, (method, answer)
                error = answer["error"]
                assert error["code"] == -32601, (method, error)
                assert "watch only" in error["message"], (method, error)
            # Nothing was done: the file is there, no other came, no job ran, no override.
            assert [f["name"] for f in await api.call("file.list")] == ["a.nc"]
            assert await api.call("job.list") == []
            faults = await api.call("fault.list", **M)
            assert not any(f["overridden"] for f in faults)
            status = await api.call("machine.status", **M)
            assert status["supervisor"] == "idle"
        finally:
            await api.close()
