"""Newline framing of one client's byte stream, with a bound on size and on time.

asyncio's `StreamReader.readline` bounds a line's size but cannot tell a
client that is quiet from one that stopped half-way through a line, and only
the second is a problem: a subscriber may say nothing for hours, but a client
that sends `{"jsonrpc":` and stalls holds a connection and a buffer while
never asking anything (a slowloris). So the framing is done here, over
`StreamReader.read`, where a partial line is visible and gets a deadline.

The clock for a partial line runs only while the server is waiting for the
rest of it: time the server spends not reading (a client at its limit of
requests in flight, whose reader is paused) is not the client's fault.
"""

from __future__ import annotations

import asyncio
from typing import Final

CHUNK: Final = 1 << 16


class LineTooLong(Exception):
    """The line in progress is over the limit (its newline not counted)."""


class LineTimeout(Exception):
    """A partial line sat unfinished for longer than the line timeout."""


class LineReader:
    """Lines of at most `max_line` bytes; a partial one must be finished within `line_timeout` s."""

    def __init__(self, reader: asyncio.StreamReader, *, max_line: int, line_timeout: float) -> None:
        self._reader = reader
        self._max_line = max_line
        self._line_timeout = line_timeout
        self._buffer = bytearray()
        self._scanned = 0  # bytes of _buffer known to hold no newline
        self._eof = False

    @property
    def pending(self) -> bool:
        """Bytes read and not yet returned as a line."""
        return bool(self._buffer)

    async def readline(self) -> bytes | None:
        """The next line without its newline; None at the end of the stream.

        A last line without a newline is still a line (as `readline` has it).
        Raises LineTooLong, LineTimeout, or OSError from the socket.
        """
        deadline: float | None = None
        while True:
            end = self._buffer.find(b"\n", self._scanned)
            if end >= 0:
                if end > self._max_line:
                    raise LineTooLong
                line = bytes(self._buffer[:end])
                del self._buffer[: end + 1]
                self._scanned = 0
                return line
            self._scanned = len(self._buffer)
            if self._scanned > self._max_line:
                raise LineTooLong
            if self._eof:
                if not self._buffer:
                    return None
                line = bytes(self._buffer)
                self._buffer.clear()
                self._scanned = 0
                return line
            if self._buffer and deadline is None:
                deadline = asyncio.get_running_loop().time() + self._line_timeout
            chunk = await self._read(deadline)
            if chunk:
                self._buffer += chunk
            else:
                self._eof = True

    async def _read(self, deadline: float | None) -> bytes:
        if deadline is None:  # between lines: a quiet client may stay quiet
            return await self._reader.read(CHUNK)
        try:
            async with asyncio.timeout_at(deadline):
                return await self._reader.read(CHUNK)
        except TimeoutError:
            raise LineTimeout from None
