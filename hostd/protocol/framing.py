"""Split a byte stream from the board into lines, without trusting it.

g2core ends every line with one LF. A board that goes mad may send no LF at
all, so a line is never allowed to grow past `max_line`: the excess is cut
off and handed on as its own (over-long) line, to be reported, not to
exhaust memory.
"""

from __future__ import annotations

# g2core's output buffer is 512 bytes; anything much longer is noise.
MAX_LINE = 4096
# `13 in data` searches for the byte; `b"\r" in data` first tries b"\r" as an integer and
# raises and clears a TypeError (CPython 3.11 `_Py_bytes_contains`): ten times the cost.
_CR = ord("\r")


class LineBuffer:
    """Bytes in, complete lines out (without the terminator, trailing CR stripped)."""

    __slots__ = ("_buf", "_discarding", "max_line")

    def __init__(self, max_line: int = MAX_LINE) -> None:
        self.max_line = max_line
        self._buf = bytearray()
        self._discarding = False

    def feed(self, data: bytes) -> list[bytes]:
        """Take received bytes; return every line they complete, in order.

        An over-long line is returned once, cut at `max_line` bytes, and the
        rest of it up to the next LF is dropped.
        """
        buf = self._buf
        if not buf and not self._discarding and data[-1:] == b"\n" and len(data) <= self.max_line:
            # Whole lines in one read, none too long: the most. grbl ends its lines in
            # CRLF: each loses one CR at its end, as `_strip_cr` takes it below (the CR
            # right before each LF; two CRLFs never overlap).
            if _CR in data:  # a byte's value: see _CR
                data = data.replace(b"\r\n", b"\n")
            return data[:-1].split(b"\n")
        lines = []
        buf += data
        start = 0
        while True:
            end = buf.find(b"\n", start)
            if end < 0:
                break
            if self._discarding:
                self._discarding = False
            else:
                line = bytes(buf[start:end])
                # Cut however the bytes arrived: whole in one read, or in pieces.
                over = len(line) > self.max_line
                lines.append(line[: self.max_line] if over else _strip_cr(line))
            start = end + 1
        del buf[:start]
        if len(buf) > self.max_line:
            if not self._discarding:
                lines.append(bytes(buf[: self.max_line]))
                self._discarding = True
            buf.clear()
        return lines

    @property
    def pending(self) -> int:
        """Bytes of an unfinished line."""
        return len(self._buf)

    def clear(self) -> None:
        self._buf.clear()
        self._discarding = False


def _strip_cr(line: bytes) -> bytes:
    return line[:-1] if line.endswith(b"\r") else line
