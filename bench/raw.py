"""The raw baseline: a bare blocking loop on the host side of the same kind of pty.

No asyncio, no daemon: it opens the slave as a serial host would (raw mode,
then a tcflush, which is what makes the instant controller send its banner),
writes the job's lines one `os.write` each, and counts one answer per line:
on g2core `{"r":` with `window` lines unanswered, on grbl `ok` with as many
bytes unanswered as the board's receive buffer holds (character counting,
127 of 128). The lines are the ones the daemon writes (numbered `N<k>` on
g2core, as the daemon numbers job lines; as they are on grbl, whose bench
boards keep no line numbers), so both send the same bytes. What the daemon
does on top of this is what the bench measures.
"""

from __future__ import annotations

import os
import select
import termios
import time
import tty
from collections import deque
from dataclasses import dataclass

from hostd.protocol.program import number_line

REALTIME_EVERY = 100  # lines between a `!` and the next, in the latency pass
RESUME_AFTER = 50  # lines after a `!` before its `~`


@dataclass
class RawResult:
    lines: int
    seconds: float
    cpu: float  # this thread's CPU seconds
    bangs_at: list[float]  # time.monotonic() right before each `!` was written


GRBL_ROOM = 127  # bytes a grbl's 128-byte receive ring holds


def wire_lines(text: str, dialect: str = "g2core") -> list[bytes]:
    """The job's lines as the daemon writes them to the bench's boards, each ending in LF:
    numbered from 1 on g2core; as they are on grbl, whose bench boards are classic
    grbl's default build (`[OPT:V,15,128]`: no line numbers, so the daemon sends none)."""
    if dialect == "grbl":
        return [line.encode() + b"\n" for line in text.splitlines()]
    return [number_line(line, i).encode() + b"\n" for i, line in enumerate(text.splitlines(), 1)]


class RawHost:
    def __init__(self, path: str, dialect: str = "g2core", timeout: float = 10.0) -> None:
        self.dialect = dialect
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.fd)
        termios.tcflush(self.fd, termios.TCIOFLUSH)
        self.buf = b""
        banner = b"SYSTEM READY" if dialect == "g2core" else b"['$' for help]"
        deadline = time.monotonic() + timeout
        while banner not in self.buf:
            if time.monotonic() > deadline:
                raise TimeoutError("no banner from the instant controller")
            ready, _, _ = select.select([self.fd], [], [], 0.1)
            if ready:
                self.buf += os.read(self.fd, 4096)
        self.buf = self.buf.split(banner, 1)[1].split(b"\n", 1)[1]

    def close(self) -> None:
        os.close(self.fd)

    def stream(self, lines: list[bytes], window: int, *, realtime: bool = False) -> RawResult:
        if self.dialect == "grbl":
            return self._stream_counted(lines)
        return self._stream_window(lines, window, realtime=realtime)

    def _stream_counted(self, lines: list[bytes]) -> RawResult:
        """grbl: write while the unanswered bytes fit the board's buffer; `ok` frees a line's."""
        fd = self.fd
        total = len(lines)
        sent = acked = used = 0
        sizes: deque[int] = deque()
        pending = self.buf
        cpu0, t0 = time.thread_time(), time.monotonic()
        while acked < total:
            while sent < total and used + len(lines[sent]) <= GRBL_ROOM:
                os.write(fd, lines[sent])
                used += len(lines[sent])
                sizes.append(len(lines[sent]))
                sent += 1
            pending += os.read(fd, 65536)
            *complete, pending = pending.split(b"\n")
            for line in complete:
                if line.startswith(b"ok"):
                    acked += 1
                    used -= sizes.popleft()
        seconds = time.monotonic() - t0
        cpu = time.thread_time() - cpu0
        self.buf = pending
        return RawResult(total, seconds, cpu, [])

    def _stream_window(
        self, lines: list[bytes], window: int, *, realtime: bool = False
    ) -> RawResult:
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
