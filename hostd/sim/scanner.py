"""The board's input scanner: bytes from one port into controls and data lines.

This is g2core's `LineRXBuffer::_scan_buffer` (xio.cpp; g2core.md sections 1,
7.1 and 8) reduced to what a host can observe:

- CR and LF end a line; runs of them collapse, so empty lines produce nothing.
- A NUL byte discards everything buffered for the port ("scan ran into NULL").
- `!` `~` 0x04 0x18 0x05 at the start of a line are single-character
  controls, recognised without waiting for a terminator; a CR/LF right after
  one is swallowed. `%` is a control while the machine has a hold (the
  caller says when) or right after a `!` (xio.cpp:754
  `_last_control_was_feedhold`, which is how `!%` works even at rest);
  otherwise it starts a data line.
- A line starting with `{` is a control line: the board runs it at once,
  ahead of data lines still waiting. Its length for the response footer
  includes the terminator bytes already received.
- Every other line is a data line, run in order when the planner has room.
- A line over 511 characters is cut at 511; the rest is skipped up to the
  next terminator.

Pure: no I/O. Events are produced lazily, so a `!` the caller acts on before
asking for the next event changes how a following `%` is classified, as on
the board, where the scanner stops at each control and the dispatcher runs
it before scanning on.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

MAX_LINE = 511
REALTIME = frozenset(b"!~\x04\x18\x05")
PERCENT = ord("%")
_TERMINATORS = b"\r\n"


@dataclass(frozen=True, slots=True)
class Realtime:
    """A single-character control."""

    char: int


@dataclass(frozen=True, slots=True)
class ControlLine:
    """A `{...}` line; `linelen` is what g2core reports in f[2] minus one."""

    text: bytes
    linelen: int


@dataclass(frozen=True, slots=True)
class DataLine:
    """A line run in order; it occupies `len(text) + 1` bytes of the RX ring."""

    text: bytes

    @property
    def size(self) -> int:
        return len(self.text) + 1


@dataclass(frozen=True, slots=True)
class NulFlush:
    """A NUL byte: the port's whole RX buffer is discarded, scanned lines included."""


ScanEvent = Realtime | ControlLine | DataLine | NulFlush


class LineScanner:
    """Scans one port's byte stream; `percent_is_control` reports a hold in progress."""

    def __init__(self, percent_is_control: Callable[[], bool]) -> None:
        self._percent_is_control = percent_is_control
        self._buf = bytearray()
        self._skipping = False  # inside the tail of an over-long line
        # xio.cpp `_last_control_was_feedhold`: a `%` right after a `!` is a control
        # whether or not a hold is on (what makes `!%` a flush on any port).
        self._after_feedhold = False

    @property
    def partial(self) -> int:
        """Bytes held that are not yet a complete line."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget everything: the port was flushed, opened or closed."""
        self._buf.clear()
        self._skipping = False
        self._after_feedhold = False

    def feed(self, data: bytes) -> Iterator[ScanEvent]:
        self._buf += data
        buf = self._buf
        while buf:
            if self._skipping:
                end = _find_terminator(buf)
                region = buf if end < 0 else buf[:end]
                if 0 in region:
                    yield from self._nul()
                    return
                if end < 0:
                    buf.clear()
                    return
                del buf[:end]
                self._skipping = False
            _drop_terminators(buf)
            if not buf:
                return
            first = buf[0]
            if first == 0:
                yield from self._nul()
                return
            percent = first == PERCENT and (self._after_feedhold or self._percent_is_control())
            if first in REALTIME or percent:
                del buf[0]
                _drop_terminators(buf)
                self._after_feedhold = first == ord("!")
                yield Realtime(first)
                continue
            self._after_feedhold = False
            end = _find_terminator(buf)
            region = buf if end < 0 else buf[:end]
            if 0 in region:
                yield from self._nul()
                return
            if end < 0:
                if len(buf) > MAX_LINE:
                    line = bytes(buf[:MAX_LINE])
                    del buf[:MAX_LINE]
                    self._skipping = True
                    yield _classify(line, 0)
                return
            line = bytes(buf[: min(end, MAX_LINE)])
            del buf[: end + 1]
            terminators = 1
            if line[:1] == b"{":
                # The board copies the terminators it has already scanned with
                # a control line, and they count in its f[2].
                before = len(buf)
                _drop_terminators(buf)
                terminators += before - len(buf)
            yield _classify(line, terminators)

    def _nul(self) -> Iterator[ScanEvent]:
        self.reset()
        yield NulFlush()


def _classify(line: bytes, terminators: int) -> ControlLine | DataLine:
    if line[:1] == b"{":
        return ControlLine(line, len(line) + terminators)
    return DataLine(line)


def _find_terminator(buf: bytearray) -> int:
    cr = buf.find(b"\r")
    lf = buf.find(b"\n")
    if cr < 0:
        return lf
    if lf < 0:
        return cr
    return min(cr, lf)


def _drop_terminators(buf: bytearray) -> None:
    n = 0
    while n < len(buf) and buf[n] in _TERMINATORS:
        n += 1
    if n:
        del buf[:n]
