"""Ctrl-C and the operator's answers, as things the event loop can wait on.

A CLI following a running machine must not die on Ctrl-C: the machine keeps
moving whatever the client does, so Ctrl-C becomes a question ("pause,
cancel or continue?") or, for `watch`, a clean exit. SIGINT is therefore
turned into an `asyncio.Event` (`CtrlC`) instead of KeyboardInterrupt, and
answers are read from stdin without a thread (`StdinLines`): a thread
blocked in `readline()` would keep the process alive at exit, since
`asyncio.run` joins its executor.

Answers are whole lines on a terminal and on a pipe alike, so tests (and
scripts) drive the prompt by writing `p\\n` to the CLI's stdin.
"""

from __future__ import annotations

import asyncio
import os
import signal
from collections.abc import Awaitable
from types import TracebackType
from typing import Self, TypeVar

T = TypeVar("T")


class CtrlC:
    """SIGINT as an event, for the duration of a `with` block (then the default again)."""

    def __init__(self) -> None:
        self.event = asyncio.Event()
        self._loop: asyncio.AbstractEventLoop | None = None

    def __enter__(self) -> Self:
        self._loop = asyncio.get_running_loop()
        self._loop.add_signal_handler(signal.SIGINT, self.event.set)
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._loop is not None:
            self._loop.remove_signal_handler(signal.SIGINT)
            self._loop = None

    @property
    def pressed(self) -> bool:
        return self.event.is_set()

    def clear(self) -> None:
        self.event.clear()


class Interrupted(Exception):
    """Ctrl-C came first."""


async def unless_interrupted(aw: Awaitable[T], ctrl_c: CtrlC, timeout: float | None = None) -> T:
    """`aw`'s result; raises Interrupted if Ctrl-C comes first, TimeoutError after `timeout`.

    A result that is ready in the same instant as Ctrl-C is still returned
    (the press stays pending for the caller's next wait): what `aw` took,
    e.g. a notification off a queue, must not be lost.
    """
    work = asyncio.ensure_future(aw)
    stop = asyncio.ensure_future(ctrl_c.event.wait())
    try:
        await asyncio.wait({work, stop}, timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
    finally:
        stop.cancel()
        await asyncio.wait({stop})  # ended here, not left to the loop
        if not work.done():
            work.cancel()
            await asyncio.wait({work})  # a cancel of our own caller still reaches it
    if work.done() and not work.cancelled():
        return work.result()
    if ctrl_c.pressed:
        raise Interrupted
    raise TimeoutError


class StdinLines:
    """Lines from a file descriptor (stdin), read as the loop sees them arrive.

    Whatever follows a newline is kept for the next question, so answers
    written ahead of time (a test feeding "p\\nr\\n") are used in order.
    """

    def __init__(self, fd: int = 0) -> None:
        self._fd = fd
        self._buffer = b""
        self._eof = False

    async def readline(self) -> str | None:
        """The next line without its newline; None at end of input."""
        while b"\n" not in self._buffer and not self._eof:
            await self._readable()
            try:
                chunk = os.read(self._fd, 4096)
            except BlockingIOError:
                continue
            except OSError:
                chunk = b""
            if not chunk:
                self._eof = True
            self._buffer += chunk
        if not self._buffer:
            return None
        line, _, self._buffer = self._buffer.partition(b"\n")
        return line.decode("utf-8", "replace").rstrip("\r")

    async def _readable(self) -> None:
        loop = asyncio.get_running_loop()
        ready = loop.create_future()

        def wake() -> None:
            if not ready.done():
                ready.set_result(None)

        try:
            loop.add_reader(self._fd, wake)
        except (OSError, ValueError):
            return  # a regular file (not pollable): reading it never blocks
        try:
            await ready
        finally:
            loop.remove_reader(self._fd)
