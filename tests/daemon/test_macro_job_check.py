"""A macro's lines pass the job check a file's would (macros.py `admit_program`, docs/api.md
macro.run): a line the machine's dialect or policy refuses, such as an M6 on a machine
with no `tool_change` policy, refuses the whole macro with 1008 before any line is sent."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.daemon.conftest import running_daemon
from tests.daemon.test_api import fails
from tests.daemon.test_operations import lines_sent

pytestmark = pytest.mark.asyncio

MACHINE = "sim1"
MACROS = [
    {"name": "swap", "text": "G21 G90\nG0 X{x}\nM6 T2", "params": {"x": {"min": 0, "max": 5}}}
]


async def test_a_macro_line_the_job_check_refuses_refuses_the_macro_unsent(
    tmp_path: Path,
) -> None:
    async with running_daemon(tmp_path, macros=MACROS) as d:
        rpc = await d.client()
        try:
            await d.idle(rpc, MACHINE)
            call = rpc.call("macro.run", machine=MACHINE, name="swap", params={"x": 1})
            err = await fails(1008, call)
            assert "M6" in err.message or "tool" in err.message, err.message
            assert not any(b"G0" in line or b"M6" in line for line in lines_sent(d, MACHINE))
            assert await rpc.call("job.list", machine=MACHINE) == []
        finally:
            await rpc.close()
