"""Stopping the daemon leaves nothing running: every task it started has ended.

`hostd serve` in this process (service.serve, as systemd starts it), a job
streaming and a client connected, then SIGTERM: once `serve` returns, the
only task left on the loop is the test's own. A task fired and forgotten
(a job's follower, a row write, the watchdog's pings, the uploads' sweep)
would still be pending, cancelled perhaps but never awaited.
"""

from __future__ import annotations

import asyncio
import gc
import os
import signal
import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from hostd.api.peer import AccessPolicy
from hostd.config import parse_config
from hostd.machine.jobstore import JobStore
from hostd.service import serve
from tests.daemon.conftest import READER, Rpc, config_data

pytestmark = pytest.mark.asyncio

LONG = "".join(f"G1 X{i % 40} Y{i % 9} F600\n" for i in range(2000))


@pytest.fixture
def notify(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[socket.socket]:
    """systemd's side: the daemon says READY=1 here, and pings its watchdog (a task)."""
    path = str(tmp_path / "notify")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.setblocking(False)
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    monkeypatch.setenv("WATCHDOG_USEC", "2000000")
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    try:
        yield sock
    finally:
        sock.close()
        gc.unfreeze()  # serve froze what it built, for a daemon's lifetime, not a test's


async def until(sock: socket.socket, want: bytes) -> None:
    loop = asyncio.get_running_loop()
    async with asyncio.timeout(20):
        while want not in await loop.sock_recv(sock, 4096):
            pass


async def test_a_stopped_daemon_leaves_no_task_behind(
    tmp_path: Path, notify: socket.socket
) -> None:
    config = parse_config(config_data(tmp_path, status_interval=0.1))
    path = config.daemon.socket
    daemon = asyncio.create_task(serve(config, path, AccessPolicy.default(), None))
    await until(notify, b"READY=1")
    await until(notify, b"sim1 idle")

    rpc = await Rpc.open(path)
    await rpc.call("subscribe", topics=["job"], machine="sim1")
    await rpc.call("file.upload", name="long.gcode", data=LONG)
    job = (await rpc.call("job.start", machine="sim1", file="long.gcode"))["job"]
    await rpc.notification(lambda n: n["params"]["job"]["lines_acked"] > 0)

    os.kill(os.getpid(), signal.SIGTERM)  # the daemon's own handler takes it
    async with asyncio.timeout(20):
        await daemon
    # At once, before anything else runs: a task cancelled but not awaited may still be here.
    mine = {asyncio.current_task()}
    left = [t for t in asyncio.all_tasks() if t not in mine and t.get_name() != READER]
    await rpc.close()
    assert left == [], f"tasks still pending after the daemon stopped: {left}"
    store = JobStore(Path(config.daemon.state_dir) / "hostd.db")
    try:
        row = await store.get(job)
    finally:
        store.close()
    assert row is not None and row.state == "interrupted" and row.lines_acked > 0
