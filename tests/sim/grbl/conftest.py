"""A host speaking raw bytes to the simulated grbl over a real pty, as a sender would."""

from __future__ import annotations

import asyncio
import contextlib
import os
import tty
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import pytest_asyncio

from hostd.sim.grbl import GrblConfig, GrblSimController

CLASSIC = GrblConfig(flavour="grbl", instant=True, reset_on_open=False)
HAL = GrblConfig(flavour="grblhal", instant=True)


class GrblHost:
    """The port opened raw (no flush, no echo): whole CRLF-terminated lines in."""

    def __init__(self, path: str) -> None:
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(self.fd)
        self.raw = bytearray()  # every byte read, untouched
        self._pos = 0

    def send(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            written = os.write(self.fd, view)
            view = view[written:]

    def _read(self) -> None:
        with contextlib.suppress(BlockingIOError):
            while chunk := os.read(self.fd, 65536):
                self.raw += chunk

    async def line(self, timeout: float = 2.0) -> str:
        """The next line, without its CRLF (which must be there)."""
        loop = asyncio.get_running_loop()
        arrived = asyncio.Event()
        loop.add_reader(self.fd, arrived.set)
        try:
            async with asyncio.timeout(timeout):
                while b"\n" not in self.raw[self._pos :]:
                    arrived.clear()
                    self._read()
                    if b"\n" not in self.raw[self._pos :]:
                        await arrived.wait()
        finally:
            loop.remove_reader(self.fd)
        end = self.raw.index(b"\n", self._pos)
        line = bytes(self.raw[self._pos : end + 1])
        self._pos = end + 1
        assert line.endswith(b"\r\n"), line
        return line[:-2].decode("latin-1")

    async def until(self, done: Callable[[str], bool], timeout: float = 2.0) -> list[str]:
        """Lines up to and including the first for which `done` is true."""
        got: list[str] = []
        async with asyncio.timeout(timeout):
            while True:
                got.append(await self.line(timeout))
                if done(got[-1]):
                    return got

    async def ask(self, line: bytes, timeout: float = 2.0) -> list[str]:
        """Send a line; everything up to its `ok` or `error:N`."""
        self.send(line)
        return await self.until(is_answer, timeout)

    async def status(self) -> str:
        self.send(b"?")
        return (await self.until(lambda s: s.startswith("<")))[-1]

    def close(self) -> None:
        os.close(self.fd)


def is_answer(line: str) -> bool:
    return line == "ok" or line.startswith("error:")


@pytest_asyncio.fixture
async def classic(tmp_path: Path) -> AsyncIterator[GrblSimController]:
    async with GrblSimController(str(tmp_path / "ttyGRBL"), CLASSIC) as sim:
        yield sim


@pytest_asyncio.fixture
async def hal(tmp_path: Path) -> AsyncIterator[GrblSimController]:
    async with GrblSimController(str(tmp_path / "ttyHAL"), HAL) as sim:
        yield sim


async def connect(sim: GrblSimController) -> GrblHost:
    """Open the port, reset the board with 0x18 and read its banner."""
    host = GrblHost(sim.path)
    await sim.wait_attached()
    host.send(b"\x18")
    await host.until(lambda s: s.startswith(("Grbl ", "GrblHAL ")))
    return host


@pytest_asyncio.fixture
async def classic_host(classic: GrblSimController) -> AsyncIterator[GrblHost]:
    host = await connect(classic)
    yield host
    host.close()


@pytest_asyncio.fixture
async def hal_host(hal: GrblSimController) -> AsyncIterator[GrblHost]:
    host = await connect(hal)
    yield host
    host.close()
