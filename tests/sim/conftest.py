"""The host side of the simulated board, without the project's link layer.

`Host` opens a port exactly as the daemon does (serialx, which ends its open
with a tcflush) and reads the board's output as JSON lines. `RawHost` opens
it with a plain `os.open`, for what serialx hides: a non-flushing opener,
EAGAIN when the board stops reading, bytes that are not JSON.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import termios
import tty
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest_asyncio
import serialx

from hostd.sim import SimConfig, SimController

Message = dict[str, Any]

# Moves finish at once: for tests about lines, responses and states.
INSTANT = SimConfig(instant=True, status_interval=0.02, feedhold_decel=0.01, boot_time=0.01)
# Moves take real (short) time: 1 mm at F600 lasts 0.1 s.
TIMED = SimConfig(status_interval=0.02, feedhold_decel=0.02, boot_time=0.01)


class Host:
    """A serialx connection to a sim port, reading one line per board message."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader = reader
        self.writer = writer

    @classmethod
    async def open(cls, path: str, *, banner: bool = True) -> Host:
        reader, writer = await serialx.open_serial_connection(url=path, baudrate=115200)
        host = cls(reader, writer)
        if banner:
            first = await host.message()
            assert first["r"]["msg"] == "SYSTEM READY", first
        return host

    def send(self, data: bytes) -> None:
        self.writer.write(data)

    async def line(self, timeout: float = 2.0) -> bytes:
        async with asyncio.timeout(timeout):
            raw = await self.reader.readline()
        if not raw.endswith(b"\n"):
            raise EOFError(f"port closed after {raw!r}")
        return raw[:-1]

    async def message(self, timeout: float = 2.0) -> Message:
        return dict(json.loads(await self.line(timeout)))

    async def until(self, done: Callable[[Message], bool], timeout: float = 2.0) -> list[Message]:
        """Messages up to and including the first for which `done` is true."""
        got: list[Message] = []
        async with asyncio.timeout(timeout):
            while True:
                got.append(await self.message(timeout=timeout))
                if done(got[-1]):
                    return got

    async def response(self, timeout: float = 2.0) -> Message:
        """The next `{r}` (status reports before it are skipped)."""
        return (await self.until(lambda m: "r" in m, timeout))[-1]

    async def ask(self, line: bytes, timeout: float = 2.0) -> Message:
        self.send(line)
        return await self.response(timeout)

    async def hangup(self, timeout: float = 2.0) -> None:
        """Read (and drop) whatever comes until the board side goes away."""
        async with asyncio.timeout(timeout):
            while True:
                try:
                    await self.line(timeout=timeout)
                except (EOFError, OSError):
                    return

    async def close(self) -> None:
        transport = self.writer.transport
        if not transport.is_closing():
            transport.abort()  # unsent bytes are dropped, as a crashing host's would be
        with contextlib.suppress(OSError, asyncio.CancelledError, TimeoutError):
            async with asyncio.timeout(2):
                await self.writer.wait_closed()


class RawHost:
    """The slave opened with plain os.open: no tcflush, non-blocking, raw.

    Raw mode is set with TCSANOW: `tty.setraw`'s default, TCSAFLUSH, flushes the
    input, which the board sees as the opener's flush.
    """

    def __init__(self, path: str) -> None:
        self.fd: int | None = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(self.fd, termios.TCSANOW)
        self._buf = bytearray()

    def write(self, data: bytes) -> int:
        assert self.fd is not None
        return os.write(self.fd, data)

    async def writable(self, timeout: float = 2.0) -> None:
        """Wait until the kernel takes bytes again (the board read some)."""
        assert self.fd is not None
        loop = asyncio.get_running_loop()
        ready = asyncio.Event()
        loop.add_writer(self.fd, ready.set)
        try:
            async with asyncio.timeout(timeout):
                await ready.wait()
        finally:
            loop.remove_writer(self.fd)

    def pending(self) -> bytes:
        """Whatever the board has written and we have not read (never waits)."""
        assert self.fd is not None
        out = bytearray()
        with contextlib.suppress(BlockingIOError):
            while chunk := os.read(self.fd, 65536):
                out += chunk
        return bytes(out)

    async def line(self, timeout: float = 2.0) -> bytes:
        assert self.fd is not None
        loop = asyncio.get_running_loop()
        arrived = asyncio.Event()
        loop.add_reader(self.fd, arrived.set)
        try:
            async with asyncio.timeout(timeout):
                while b"\n" not in self._buf:
                    arrived.clear()
                    self._buf += self.pending()
                    if b"\n" not in self._buf:
                        await arrived.wait()
        finally:
            loop.remove_reader(self.fd)
        line, _, rest = bytes(self._buf).partition(b"\n")
        self._buf = bytearray(rest)
        return line

    async def message(self, timeout: float = 2.0) -> Message:
        return dict(json.loads(await self.line(timeout)))

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def is_link(path: str | Path) -> bool:
    """Whether the port's symlink is there (a plain function: a quick, local syscall)."""
    return os.path.islink(path)


def responses(messages: list[Message]) -> list[Message]:
    return [m for m in messages if "r" in m]


def states(messages: list[Message]) -> list[int]:
    """Every `stat` the messages reported, in order."""
    out: list[int] = []
    for m in messages:
        report = m.get("sr") or (m.get("r") or {}).get("sr") or {}
        if "stat" in report:
            out.append(report["stat"])
    return out


def has_stat(*codes: int) -> Callable[[Message], bool]:
    return lambda m: "stat" in m.get("sr", {}) and m["sr"]["stat"] in codes


@pytest_asyncio.fixture
async def sim(tmp_path: Path) -> AsyncIterator[SimController]:
    async with SimController(str(tmp_path / "ttyG2"), config=INSTANT) as board:
        yield board


@pytest_asyncio.fixture
async def timed_sim(tmp_path: Path) -> AsyncIterator[SimController]:
    async with SimController(str(tmp_path / "ttyG2"), config=TIMED) as board:
        yield board


@pytest_asyncio.fixture
async def host(sim: SimController) -> AsyncIterator[Host]:
    h = await Host.open(sim.data_path)
    yield h
    await h.close()


@pytest_asyncio.fixture
async def timed_host(timed_sim: SimController) -> AsyncIterator[Host]:
    h = await Host.open(timed_sim.data_path)
    yield h
    await h.close()


@contextlib.asynccontextmanager
async def dual(
    tmp_path: Path, config: SimConfig
) -> AsyncIterator[tuple[SimController, Host, RawHost]]:
    """A board on two ports: control opened first (it gets all output), then data."""
    async with SimController(
        str(tmp_path / "data"), control_path=str(tmp_path / "ctrl"), config=config
    ) as sim:
        assert sim.control_path is not None
        control = await Host.open(sim.control_path)
        data = RawHost(sim.data_path)
        try:
            await sim.wait_attached(port="data")
            yield sim, control, data
        finally:
            data.close()
            await control.close()
