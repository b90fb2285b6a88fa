"""A macro parameter's value is written by the daemon, never by the client (macros.py,
docs/api.md macro.run): as a plain decimal of at most four places, never an exponent, so a
tiny value is a zero and not `1e-05`; and a whole-number parameter takes whole numbers
only, refused (-32602) before anything is sent rather than cut to one."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest
import pytest_asyncio

from tests.daemon.conftest import Rpc, Running, running_daemon
from tests.daemon.test_api import fails, job_end
from tests.daemon.test_operations import lines_sent

pytestmark = pytest.mark.asyncio

MACHINE = "sim1"
MACROS = [
    {
        "name": "nudge",
        "text": "G21 G90\nG0 X{x}\nG4 P{n}",
        "params": {"x": {"min": -5, "max": 5}, "n": {"min": 0, "max": 2, "integer": True}},
    }
]


@pytest_asyncio.fixture
async def hostd(tmp_path: Path) -> AsyncIterator[tuple[Running, Rpc]]:
    async with running_daemon(tmp_path, macros=MACROS) as d:
        rpc = await d.client()
        await rpc.call("subscribe", topics=["job"], machine=MACHINE)
        await d.idle(rpc, MACHINE)
        yield d, rpc
        await rpc.close()


@pytest.mark.parametrize(
    ("x", "written"),
    [(0.00001, b"G0 X0"), (-0.00004, b"G0 X0"), (1.23456, b"G0 X1.2346"), (2.5e-3, b"G0 X0.0025")],
)
async def test_a_value_is_written_as_a_plain_decimal_never_an_exponent(
    hostd: tuple[Running, Rpc], x: float, written: bytes
) -> None:
    d, rpc = hostd
    job = await rpc.call("macro.run", machine=MACHINE, name="nudge", params={"x": x, "n": 1})
    ended = await job_end(rpc, job["job"])
    assert ended["state"] == "completed", ended
    moves = [line for line in lines_sent(d, MACHINE) if b"G0" in line]
    assert len(moves) == 1 and moves[0].endswith(written), moves
    assert b"e" not in moves[0].lower()


async def test_a_whole_number_param_refuses_a_fraction_and_sends_nothing(
    hostd: tuple[Running, Rpc],
) -> None:
    d, rpc = hostd
    call = rpc.call("macro.run", machine=MACHINE, name="nudge", params={"x": 1, "n": 1.5})
    err = await fails(-32602, call)
    assert "whole number" in err.message
    assert not any(b"G0" in line or b"G4" in line for line in lines_sent(d, MACHINE))
    assert await rpc.call("job.list", machine=MACHINE) == []
