"""A jog's bound holds in the units the board is in (guard.py, docs/api.md machine.jog):
after a G20 a distance is in inches, so 400 (10,160 mm) is past the 10,000 mm no
machine's travel reaches and is refused by `machine.jog` with nothing sent;
an axis no machine has is refused too."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.daemon.conftest import G2, GRBL, running_daemon
from tests.daemon.test_api import fails
from tests.daemon.test_guard import reached

pytestmark = pytest.mark.asyncio

ABSURD = {"refusal": "maintenance", "maintenance": "absurd-jog"}


async def test_a_jog_past_any_travel_in_inches_is_refused(tmp_path: Path) -> None:
    async with running_daemon(tmp_path) as d:
        rpc = await d.client()
        try:
            await d.idle(rpc, G2)
            await rpc.call("subscribe", topics=["status"], machine=G2)
            await rpc.call("machine.send", machine=G2, line="G20")
            await rpc.notification(
                lambda n: n["method"] == "status" and '"units": "in"' in json.dumps(n)
            )
            jog = rpc.call("machine.jog", machine=G2, axes={"x": 400}, feed=10)
            assert (await fails(-32602, jog)).data == ABSURD
            assert not reached(d, G2, "X400")
            odd = rpc.call("machine.jog", machine=G2, axes={"q": 1}, feed=10)
            assert "unknown axes" in (await fails(-32602, odd)).message
            await rpc.call("machine.send", machine=G2, line="G21")
        finally:
            await rpc.close()


async def test_grbl_knows_a_g20_sent_to_it_and_bounds_its_jogs_in_inches(tmp_path: Path) -> None:
    """grbl says its units only in `$G`: after a client's G20 the session reads them back,
    so a 10-unit jog is 254 mm, past the 200 mm of `$130`, and refused; before, the host
    still took it for 10 mm and sent it (the board would have run 10 inches)."""
    async with running_daemon(tmp_path, machines=2, per_machine=[{}, {"dialect": "grbl"}]) as d:
        rpc = await d.client()
        try:
            await d.idle(rpc, GRBL)
            await rpc.call("subscribe", topics=["status"], machine=GRBL)
            await rpc.call("machine.send", machine=GRBL, line="G20")
            await rpc.notification(
                lambda n: n["method"] == "status" and n["params"]["snapshot"]["units"] == "in"
            )
            jog = rpc.call("machine.jog", machine=GRBL, axes={"x": 10}, feed=10)
            assert (await fails(-32602, jog)).data == ABSURD
            assert not reached(d, GRBL, "X10")
            await rpc.call("machine.send", machine=GRBL, line="G21")
            await rpc.notification(
                lambda n: n["method"] == "status" and n["params"]["snapshot"]["units"] == "mm"
            )
            job = await rpc.call("machine.jog", machine=GRBL, axes={"x": -10}, feed=100)
            assert job["job"]  # 10 mm fits: sent
        finally:
            await rpc.close()
