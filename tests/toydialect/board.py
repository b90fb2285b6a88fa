"""A tiny simulated toy board on a real pseudo-terminal (hostd/sim/ptyport.py's PtyPort).

It reads the toy protocol (tests/toydialect/__init__.py) a line at a time:
moves set the position at once, `ALARM` raises alarm 1, `UNLOCK` leaves it,
and every other word is `err 1`. Realtime bytes are picked out of the stream
wherever they are: `?` a report, `!` a hold, `~` its end, 0x18 a reset (the
banner again, the alarm kept: a reset is no unlock).
"""

from __future__ import annotations

import re

from hostd.sim.ptyport import PtyPort
from tests.toydialect.words import LOCKED, MAX_LINE

_WORD = re.compile(r"([A-Z])(-?[0-9]*\.?[0-9]*)")
BANNER = b"hello toy 1\n"
READ_AHEAD = 4096  # bytes taken from the host at a time


class ToyBoard:
    """The toy board; `received` holds every line it read, `alarm()` trips a limit."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.state = "IDLE"
        self.position = {"X": 0.0, "Y": 0.0, "Z": 0.0}
        self.line = 0
        self.received: list[bytes] = []
        self._buffer = bytearray()
        self._port: PtyPort | None = None

    async def start(self) -> None:
        self._port = PtyPort("data", self.path, self)
        self._port.plug()

    async def close(self) -> None:
        if self._port is not None:
            self._port.unplug()
            self._port = None

    def alarm(self, code: int = 2) -> None:
        """The board raises an alarm of its own (a limit switch, say)."""
        self.state = "ALARM"
        self._write(b"alarm %d\n" % code)

    # -- the port's listener ---------------------------------------------------

    def port_attached(self, port: PtyPort) -> None:
        self._buffer.clear()
        port.set_read_limit(READ_AHEAD)

    def port_detached(self, port: PtyPort) -> None:
        self._buffer.clear()

    def port_flushed(self, port: PtyPort) -> None:
        pass

    def port_drained(self, port: PtyPort) -> None:
        pass

    def port_data(self, port: PtyPort, data: bytes) -> None:
        port.set_read_limit(READ_AHEAD)  # the toy reads as fast as the host writes
        for byte in data:
            char = bytes([byte])
            if char == b"?":
                self._report()
            elif char == b"!":
                self.state = "HOLD" if self.state in ("IDLE", "RUN") else self.state
            elif char == b"~":
                self.state = "IDLE" if self.state == "HOLD" else self.state
            elif char == b"\x18":
                self._buffer.clear()
                self.state = "ALARM" if self.state == "ALARM" else "IDLE"
                self._write(BANNER)
            elif char == b"\n":
                line = bytes(self._buffer)
                self._buffer.clear()
                if line.strip():
                    self.received.append(line)
                    self._write(self._answer(line.decode("ascii", "replace").strip().upper()))
            elif char != b"\r":
                self._buffer += char

    # -- the protocol ----------------------------------------------------------

    def _answer(self, line: str) -> bytes:
        if len(line) + 1 > MAX_LINE:
            return b"err 3\n"
        if line == "UNLOCK":
            self.state = "IDLE" if self.state == "ALARM" else self.state
            return b"ok\n"
        if line == "ALARM":
            self.state = "ALARM"
            return b"ok\nalarm 1\n"
        if self.state == "ALARM":
            return b"err %d\n" % LOCKED
        words = _WORD.findall(line.replace(" ", ""))
        if "".join(a + b for a, b in words) != line.replace(" ", ""):
            return b"err 1\n"
        target = dict(self.position)
        for letter, number in words:
            if not number or number in ("-", ".", "-."):
                return b"err 2\n"
            if letter == "N":
                self.line = int(float(number))
            elif letter == "G" and number in ("0", "1", "4"):
                continue
            elif letter in "XYZ":
                target[letter] = float(number)
            elif letter not in "FP":
                return b"err 1\n"
        self.position = target  # the toy moves at once
        return b"ok\n"

    def _report(self) -> None:
        x, y, z = (self.position[a] for a in "XYZ")
        self._write(f"<{self.state} {x:.3f} {y:.3f} {z:.3f} {self.line}>\n".encode())

    def _write(self, data: bytes) -> None:
        if self._port is not None:
            self._port.write(data)


def simulator(data: str, control: str | None, speed: float, history: int) -> ToyBoard:
    """The factory the toy's registry entry names (`simulator`)."""
    return ToyBoard(data)
