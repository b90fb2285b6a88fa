"""The raw baseline: a bare blocking loop on the host side of the same kind of pty.

No asyncio, no daemon: it opens the slave as a serial host would (raw mode,
then a tcflush, which is what makes the instant controller send its banner),
writes the job's lines one `os.write` each keeping `window` unanswered, and
counts one `{"r":` answer per line. What the daemon does on top of this is
what the bench measures.
"""

from __future__ import annotations

import os
import select
import termios
import time
import tty
from dataclasses import dataclass

REALTIME_EVERY = 100  # lines between a `!` and the next, in the latency pass
RESUME_AFTER = 50  # lines after a `!` before its `~`


@dataclass
class RawResult:
    lines: int
    seconds: float
    cpu: float  # this thread's CPU seconds
    bangs_at: list[float]  # time.monotonic() right before each `!` was written


class RawHost:
    def __init__(self, path: str, timeout: float = 10.0) -> None:
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.fd)
        termios.tcflush(self.fd, termios.TCIOFLUSH)
        self.buf = b""
        deadline = time.monotonic() + timeout
        while b"SYSTEM READY" not in self.buf:
            if time.monotonic() > deadline:
                raise TimeoutError("no banner from the instant controller")
            ready, _, _ = select.select([self.fd], [], [], 0.1)
            if ready:
                self.buf += os.read(self.fd, 4096)
        self.buf = self.buf.split(b"SYSTEM READY", 1)[1].split(b"\n", 1)[1]

    def close(self) -> None:
        os.close(self.fd)

    def stream(self, lines: list[bytes], window: int, *, realtime: bool = False) -> RawResult:
        """Send every line (each ending in LF), `window` in flight; one answer frees one slot.

        With `realtime`, a `!` every REALTIME_EVERY lines and a `~` RESUME_AFTER
        lines later, as the daemon's feedhold/cycle_start would write them.
        """
        fd = self.fd
        total = len(lines)
        sent = acked = 0
        bangs: list[float] = []
        hold_until = -1
        pending = self.buf
        cpu0, t0 = time.thread_time(), time.monotonic()
        while acked < total:
            while sent < total and sent - acked < window:
                os.write(fd, lines[sent])
                sent += 1
                last_hold = sent + RESUME_AFTER + window >= total  # let every `~` be read too
                if realtime and sent % REALTIME_EVERY == 0 and hold_until < 0 and not last_hold:
                    bangs.append(time.monotonic())
                    os.write(fd, b"!\n")
                    hold_until = sent + RESUME_AFTER
                elif realtime and sent == hold_until:
                    os.write(fd, b"~\n")
                    hold_until = -1
            pending += os.read(fd, 65536)
            *complete, pending = pending.split(b"\n")
            for line in complete:
                if line.startswith(b'{"r":'):
                    acked += 1
        seconds = time.monotonic() - t0
        cpu = time.thread_time() - cpu0
        self.buf = pending
        return RawResult(total, seconds, cpu, bangs)
