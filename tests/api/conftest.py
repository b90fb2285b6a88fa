"""A real ApiServer on a Unix socket in tmp_path, serving a few dummy methods."""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import pytest_asyncio
from pydantic import BaseModel, ConfigDict

from hostd.api.client import current_client
from hostd.api.rpc import Methods, encode_notification
from hostd.api.server import ApiServer

TIMEOUT = 5.0


class _Params(BaseModel):
    model_config = ConfigDict(extra="forbid")


class EchoParams(_Params):
    text: str


class AddParams(_Params):
    a: int
    b: int


class FloodParams(_Params):
    count: int
    size: int = 0


class TellParams(_Params):
    count: int


class MachineStyleError(Exception):
    """Shaped like the machine layer's errors: `code`, `message`, `data`, no RpcError base."""

    def __init__(self, code: int, message: str, data: Any = None) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.data = data


@dataclass
class Harness:
    """The dummy methods and the levers and signals the tests hold."""

    methods: Methods = field(default_factory=Methods)
    release: asyncio.Event = field(default_factory=asyncio.Event)
    slow_started: asyncio.Event = field(default_factory=asyncio.Event)
    disconnected: asyncio.Event = field(default_factory=asyncio.Event)
    told: asyncio.Event = field(default_factory=asyncio.Event)  # `tell` has told them all
    counted: int = 0
    order: list[str] = field(default_factory=list)  # `note` and `mark` calls, as run
    running: int = 0  # `slow` calls under way
    peak: int = 0  # the most `slow` calls ever under way at once

    def __post_init__(self) -> None:
        m = self.methods
        m.register("echo", EchoParams, self.echo)
        m.register("add", AddParams, self.add)
        m.register("slow", None, self.slow)
        m.register("boom", None, self.boom)
        m.register("refuse", None, self.refuse)
        m.register("count", None, self.count)
        m.register("whoami", None, self.whoami)
        m.register("flood", FloodParams, self.flood)
        m.register("tell", TellParams, self.tell)
        m.register("note", None, self.note)
        m.register("machine.mark", None, self.mark, immediate=True)

    async def note(self) -> str:
        self.order.append("note")
        return "noted"

    async def mark(self) -> str:
        """Shaped like a realtime method: never suspends, answered as it arrives."""
        self.order.append("mark")
        return "marked"

    async def echo(self, p: EchoParams) -> EchoParams:
        return p  # a pydantic model as the result: serialised with model_dump

    async def add(self, p: AddParams) -> int:
        return p.a + p.b

    async def slow(self) -> str:
        self.running += 1
        self.peak = max(self.peak, self.running)
        self.slow_started.set()
        try:
            await self.release.wait()
        finally:
            self.running -= 1
        return "slow done"

    async def boom(self) -> None:
        raise RuntimeError("kaboom")

    async def refuse(self) -> None:
        raise MachineStyleError(1003, "machine busy", {"supervisor": "operation"})

    async def count(self) -> int:
        self.counted += 1
        return self.counted

    async def whoami(self) -> dict[str, int]:
        """The caller as the server saw it; also watches for its disconnect."""
        client = current_client()
        client.on_disconnect.append(self.disconnected.set)
        return {"pid": client.pid, "uid": client.uid, "gid": client.gid}

    async def tell(self, p: TellParams) -> int:
        """Tell the caller `count` topic notifications, each from a loop pass of its own,
        as a machine's events reach a subscriber."""
        client = current_client()
        for i in range(p.count):
            client.send_notice(encode_notification("tick", {"i": i}))
            await asyncio.sleep(0)
        self.told.set()
        return p.count

    async def flood(self, p: FloodParams) -> int:
        """Notify the caller `count` times, yielding now and then as a live machine would."""
        client = current_client()
        client.on_disconnect.append(self.disconnected.set)
        pad = "x" * p.size
        for i in range(p.count):
            if client.closed:
                return i
            client.notify("tick", {"i": i, "pad": pad})
            if i % 50 == 49:
                await asyncio.sleep(0)
        return p.count


class Conn:
    """A test client on a real connection: raw bytes out, parsed JSON lines in."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader = reader
        self.writer = writer

    @classmethod
    async def open(cls, path: str | Path) -> Conn:
        reader, writer = await asyncio.open_unix_connection(path, limit=1 << 24)
        return cls(reader, writer)

    def stop_reading(self) -> None:
        """Stop taking data off the socket, like a client that hung: the kernel buffers fill."""
        cast(asyncio.Transport, self.writer.transport).pause_reading()

    async def send_raw(self, data: bytes) -> None:
        self.writer.write(data)
        async with asyncio.timeout(TIMEOUT):
            await self.writer.drain()

    async def send(self, message: Any) -> None:
        await self.send_raw(json.dumps(message).encode() + b"\n")

    async def recv(self) -> Any:
        async with asyncio.timeout(TIMEOUT):
            line = await self.reader.readline()
        assert line.endswith(b"\n"), f"connection ended instead: {line!r}"
        return json.loads(line)

    async def call(self, method: str, params: Any = None, id: int | str = 1) -> Any:
        request: dict[str, Any] = {"jsonrpc": "2.0", "method": method, "id": id}
        if params is not None:
            request["params"] = params
        await self.send(request)
        return await self.recv()

    async def closed_by_server(self) -> bool:
        """True once the server has ended the connection, whatever was still in flight."""
        async with asyncio.timeout(TIMEOUT):
            try:
                while await self.reader.read(1 << 16):
                    pass
            except ConnectionResetError:
                pass
        return True

    async def close(self) -> None:
        self.writer.close()
        with contextlib.suppress(OSError):
            await self.writer.wait_closed()


@pytest_asyncio.fixture
async def harness() -> Harness:
    return Harness()


@contextlib.asynccontextmanager
async def serving(harness: Harness, path: Path, **options: Any) -> AsyncIterator[ApiServer]:
    async with ApiServer(harness.methods, **options) as server:
        await server.start(path)
        yield server


@pytest_asyncio.fixture
async def server(harness: Harness, tmp_path: Path) -> AsyncIterator[ApiServer]:
    async with serving(harness, tmp_path / "api.sock") as server:
        yield server


@pytest_asyncio.fixture
async def conn(server: ApiServer) -> AsyncIterator[Conn]:
    assert server.path is not None
    c = await Conn.open(server.path)
    yield c
    await c.close()
