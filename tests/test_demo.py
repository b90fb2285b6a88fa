"""`make demo` as a newcomer runs it: the job completes, the dashboard stays up until Ctrl-C."""

from __future__ import annotations

import asyncio
import os
import re
import signal
import sys

import aiohttp
import pytest

from hostd.cli.client import Client

pytestmark = [pytest.mark.asyncio, pytest.mark.timeout(120)]


async def test_the_demo_runs_its_job_then_keeps_the_dashboard_up_until_ctrl_c() -> None:
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "hostd.demo",
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.STDOUT,
        env={**os.environ, "COLUMNS": "200", "NO_COLOR": "1"},
    )
    assert proc.stdout is not None
    seen: list[str] = []
    try:
        async with asyncio.timeout(90):
            while not any("Ctrl-C stops the demo" in line for line in seen):
                raw = await proc.stdout.readline()
                assert raw, "the demo ended before it said how to stop it:\n" + "".join(seen)
                seen.append(raw.decode())
        text = "".join(seen)
        assert "job #1 completed" in text
        url = re.search(r"dashboard:\s+(http://\S+)", text)
        assert url, text
        # The job is over, and the link the demo printed still answers.
        async with aiohttp.ClientSession() as http, http.get(url.group(1)) as page:
            assert page.status == 200
        socket_path = re.search(r"export HOSTD_SOCKET=(\S+)", text)
        assert socket_path
        async with Client(socket_path.group(1)) as client:  # what it suggests reaches the daemon
            assert (await client.call("daemon.info"))["machines"] == ["sim1"]
        proc.send_signal(signal.SIGINT)
        out, _ = await asyncio.wait_for(proc.communicate(), 30)
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    assert proc.returncode == 0, out.decode()
    assert "stopped cleanly" in out.decode()
