"""A bare pseudo-terminal peer for testing the link layer on its own."""

from __future__ import annotations

import asyncio
import contextlib
import os
import tty
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import pytest_asyncio


class PtyPeer:
    """The master side of a pty pair, with the slave reachable at `path` (a symlink)."""

    def __init__(self, path: Path) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        self.name = os.ttyname(slave)
        os.close(slave)  # or the host closing is never visible
        os.set_blocking(master, False)
        self.master: int | None = master
        self.path = path
        path.symlink_to(self.name)
        self.received = bytearray()
        self._arrived = asyncio.Event()
        self._reading = False

    def write(self, data: bytes) -> None:
        assert self.master is not None
        view = memoryview(data)
        while view:
            view = view[os.write(self.master, view) :]

    def start_reading(self) -> None:
        assert self.master is not None
        asyncio.get_running_loop().add_reader(self.master, self._on_readable)
        self._reading = True

    def stop_reading(self) -> None:
        if self._reading and self.master is not None:
            asyncio.get_running_loop().remove_reader(self.master)
        self._reading = False

    def _on_readable(self) -> None:
        assert self.master is not None
        try:
            self.received += os.read(self.master, 65536)
        except OSError:  # EIO: the host closed its end
            self.stop_reading()
        self._arrived.set()

    async def wait_received(self, data: bytes) -> None:
        async with asyncio.timeout(5):
            while data not in self.received:
                self._arrived.clear()
                await self._arrived.wait()

    async def wait_length(self, size: int) -> None:
        async with asyncio.timeout(5):
            while len(self.received) < size:
                self._arrived.clear()
                await self._arrived.wait()

    def unplug(self) -> None:
        """What a pulled USB cable looks like: the device and its name vanish."""
        self.stop_reading()
        if self.master is not None:
            os.close(self.master)
            self.master = None
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()


@pytest_asyncio.fixture
async def peers(tmp_path: Path) -> AsyncIterator[Iterator[PtyPeer]]:
    made: list[PtyPeer] = []

    def factory() -> Iterator[PtyPeer]:
        while True:
            peer = PtyPeer(tmp_path / f"tty{len(made)}")
            made.append(peer)
            yield peer

    yield factory()
    for peer in made:
        peer.unplug()
