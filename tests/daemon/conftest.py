"""A whole daemon (simulated machine, job store, API socket) and a raw JSON-RPC client."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest_asyncio

from hostd.api.methods import Api, build_methods
from hostd.api.server import ApiServer
from hostd.config import parse_config
from hostd.daemon import Daemon

READER = "test-rpc-reader"  # a test client's task, the test's own


class RpcFailure(Exception):
    def __init__(self, error: dict[str, Any]) -> None:
        super().__init__(f"{error['code']}: {error['message']}")
        self.code: int = error["code"]
        self.message: str = error["message"]
        self.data: Any = error.get("data")


class Rpc:
    """One connection: calls matched by id, notifications queued in order."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self._ids = itertools.count(1)
        self._waiting: dict[int, asyncio.Future[dict[str, Any]]] = {}
        self.notifications: asyncio.Queue[dict[str, Any]] = asyncio.Queue()
        self._task = asyncio.create_task(self._read(), name=READER)

    @classmethod
    async def open(cls, path: str) -> Rpc:
        reader, writer = await asyncio.open_unix_connection(path, limit=8 * 1024 * 1024)
        return cls(reader, writer)

    async def _read(self) -> None:
        while line := await self.reader.readline():
            msg = json.loads(line)
            if "id" in msg and msg["id"] in self._waiting:
                self._waiting.pop(msg["id"]).set_result(msg)
            elif "method" in msg:
                self.notifications.put_nowait(msg)

    async def call(self, method: str, **params: Any) -> Any:
        msg_id = next(self._ids)
        future = asyncio.get_running_loop().create_future()
        self._waiting[msg_id] = future
        request = {"jsonrpc": "2.0", "id": msg_id, "method": method}
        if params:
            request["params"] = params
        self.writer.write(json.dumps(request).encode() + b"\n")
        # A bound for a test that would otherwise hang, not a timing check: job.start and
        # file.analyze wait on a worker process (its start, a 60,000-line file), which took
        # past 15 s with the suite's four workers and other load on two cores.
        async with asyncio.timeout(30):
            msg = await future
        if "error" in msg:
            raise RpcFailure(msg["error"])
        return msg["result"]

    async def notification(
        self, predicate: Callable[[dict[str, Any]], bool], timeout: float = 30
    ) -> dict[str, Any]:
        # A bound for a test that would otherwise hang, not a timing check: generous, since
        # a job's first line waits for its file check on a worker process (seconds when
        # six test workers share two cores).
        async with asyncio.timeout(timeout):
            while True:
                msg = await self.notifications.get()
                if predicate(msg):
                    return msg

    async def ended(self) -> None:
        """Until the daemon has ended the connection and everything it sent is read."""
        await asyncio.wait({self._task})

    def queued(self) -> list[dict[str, Any]]:
        """The notifications received and not yet taken, taken now, in order."""
        taken = []
        while not self.notifications.empty():
            taken.append(self.notifications.get_nowait())
        return taken

    async def close(self) -> None:
        self._task.cancel()
        await asyncio.wait({self._task})  # the reader ends here: no task outlives its client
        self.writer.close()
        with contextlib.suppress(Exception):
            await self.writer.wait_closed()


@dataclass
class Running:
    daemon: Daemon
    api: Api
    socket: str
    jobs: Path

    async def client(self) -> Rpc:
        return await Rpc.open(self.socket)

    async def idle(self, rpc: Rpc, machine: str = "sim1") -> None:
        """Until the machine's supervisor is idle (told by the supervisor topic)."""
        watcher = await self.client()
        try:
            await watcher.call("subscribe", topics=["supervisor"], machine=machine)
            if (await watcher.call("machine.status", machine=machine))["supervisor"] != "idle":
                await watcher.notification(lambda n: n["params"]["to"] == "idle")
        finally:
            await watcher.close()


def config_data(
    tmp_path: Path, machines: int = 1, daemon: dict[str, Any] | None = None, **extra: Any
) -> dict[str, Any]:
    """`extra` goes to every machine, `daemon` to `[daemon]`."""
    return {
        "daemon": {
            "socket": str(tmp_path / "hostd.sock"),
            "state_dir": str(tmp_path / "state"),
            # A worker process for every test's daemon would cost the suite minutes of CPU:
            # tests/machine/test_workers.py and the daemon test of prewarming turn it on.
            "prewarm_workers": False,
            # The suite's own processes keep the cores busy: a niced worker would starve.
            "analysis_nice": 0,
            **(daemon or {}),
        },
        "machines": [
            {
                "id": f"sim{i}",
                "data_port": "sim",
                "status_interval": 0.1,
                "auto_connect": True,
                **extra,
            }
            for i in range(1, machines + 1)
        ],
    }


@contextlib.asynccontextmanager
async def running_daemon(
    tmp_path: Path,
    machines: int = 1,
    daemon: dict[str, Any] | None = None,
    clock: Callable[[], float] = time.monotonic,
    per_machine: list[dict[str, Any]] | None = None,
    **extra: Any,
) -> AsyncIterator[Running]:
    """Started as `hostd serve` starts it (service.py); `clock` times uploads' expiry.

    `per_machine[i]` goes to machine i only (a dialect, say).
    """
    data = config_data(tmp_path, machines, daemon, **extra)
    for machine, own in zip(data["machines"], per_machine or [], strict=False):
        machine.update(own)
    config = parse_config(data)
    hostd = Daemon(config)
    api = Api(hostd, clock=clock)
    server = ApiServer(build_methods(api))
    socket = config.daemon.socket
    up = asyncio.Event()

    async def ready() -> None:
        await asyncio.to_thread(api.jobs.clean)
        api.attach()
        await server.start(socket)
        up.set()

    task = asyncio.create_task(hostd.run(ready))
    async with asyncio.timeout(10):
        await up.wait()
    try:
        yield Running(hostd, api, socket, hostd.jobs_dir)
    finally:
        hostd.stop()
        await task
        await server.close()


@pytest_asyncio.fixture
async def hostd(tmp_path: Path) -> AsyncIterator[Running]:
    async with running_daemon(tmp_path) as running:
        yield running


G2, GRBL = "sim1", "sim2"  # `both`'s machines: a simulated g2core and a simulated grbl


@pytest_asyncio.fixture
async def both(tmp_path: Path) -> AsyncIterator[tuple[Running, Rpc]]:
    """A daemon of two machines, sim1 (g2core) and sim2 (grbl), both idle, and a client."""
    async with running_daemon(tmp_path, machines=2, per_machine=[{}, {"dialect": "grbl"}]) as d:
        client = await d.client()
        for machine in (G2, GRBL):
            await d.idle(client, machine)
        yield d, client
        await client.close()


@pytest_asyncio.fixture
async def rpc(hostd: Running) -> AsyncIterator[Rpc]:
    client = await hostd.client()
    await hostd.idle(client)
    yield client
    await client.close()
