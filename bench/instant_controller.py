"""An "instant" g2core: answers every line at once, from a blocking os.read/os.write loop.

It sits on the master side of a pty pair whose slave is reachable through a
symlink (`--link`), like a /dev/serial/by-id link, so that a daemon (or the
raw baseline loop) opens it as a serial port. It is a separate process so
that what it costs is not charged to the host being measured.

What it does, just enough like g2core for the daemon's handshake and jobs:

- The host's open ends with a tcflush, which discards anything written
  before it: the open is detected in pty packet mode (TIOCPKT), as the
  flush status packet, and only then is the SYSTEM READY banner written.
  While no host has the slave open the master polls POLLHUP; that is
  watched with a short poll, never with a blocking read.
- Every line gets one `{"r":...,"f":[1,0,N]}` (body `{"n":L}` for a line
  numbered `N<L>`, as g2core at jv 4; N: the line's length + 1,
  + 2 for a `{`-line, as the daemon's line-mode sender expects). A GET of
  `sr` (`{"sr":null}`, which is also what the daemon makes of `?` and
  `{"sr":n}`) is answered with the current `stat`, a GET of any other key
  with 0 (`{"r":{"xvm":0},"f":[1,0,13]}`); SETs are echoed.
- The first G-code line of a job sends `{"sr":{"stat":5}}`; the expected
  number of lines (`expect N` on stdin; the report follows 10 ms after the
  last line's answer, as a board's follows its last move), or a short idle,
  `{"sr":{"stat":3}}`.
- Realtime bytes: `!` (its arrival time is recorded with time.monotonic(),
  which is CLOCK_MONOTONIC and shared with the host on the same machine)
  holds (stat 6), `~` resumes (stat 5), 0x04 and `%` in a hold end the job
  (stat 4 / 3).

Commands, one a line on stdin; answers on stdout:

- `expect N`: the next job has N lines.
- `sr COUNT RATE`: write `{"sr":{"posx":k}}` for k = 1..COUNT at RATE per
  second, recording the time just before each write.
- `dump`: one JSON line `{"bangs": [t, ...], "sr": [[k, t], ...], "lines": n,
  "sched": how it is scheduled}`, then forget them.

A board is hardware of its own, never kept off its CPU by the host's other
processes; this process stands in for one on a CPU it shares with the bench's
clients (50 subscribers reading in P2). So it asks for SCHED_FIFO (priority
10): when a byte arrives it runs at once instead of after the readers' time
slice, and a `!` is timed when a board would have read it. It blocks in every
read, so it never holds the CPU. Without the privilege it tries nice -10, and
says which it got (`sched`).
- `quit`.

It prints `listening` once the link exists and `opened` each time a host
has opened the port and been sent its banner.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import fcntl
import json
import os
import re
import select
import struct
import sys
import termios
import time
import tty
from typing import Any

BANNER = (
    b'{"r":{"fv":0.99,"fb":101.06,"hp":"bench","hv":"bench","id":"bench",'
    b'"msg":"SYSTEM READY"},"f":[1,0,1]}\n'
)
FLUSH_BITS = 0x01 | 0x02  # TIOCPKT_FLUSHREAD | TIOCPKT_FLUSHWRITE
ATTACH_POLL = 0.001  # s between looks for a host while none has the port open
BANNER_FALLBACK = 0.05  # s: a host that opens without a tcflush still gets its banner
IDLE_STOP = 0.2  # s without a G-code line while running: the job is over
# s from the job's last line to its stop report: a board reports the stop once the last
# move has run, well after answering the line (and the daemon checks for an underflow
# if a stop comes while it still has lines to send).
STOP_DELAY = 0.01

STOP, END, RUN, HOLD = 3, 4, 5, 6
REALTIME = frozenset(b"!~%\x04\x18\x05")
_LINE_NUMBER = re.compile(rb"[Nn]([0-9]+)")


class Controller:
    def __init__(self, link: str) -> None:
        self.link = link
        master, slave = os.openpty()
        tty.setraw(slave)
        name = os.ttyname(slave)
        os.close(slave)  # while we hold a slave fd the master never sees the host go
        fcntl.ioctl(master, termios.TIOCPKT, struct.pack("i", 1))
        self.fd = master
        tmp = f"{link}.{os.getpid()}.tmp"
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        os.symlink(name, tmp)
        os.replace(tmp, link)
        self.attached = False
        self.flushed = False  # the current opener's tcflush has been seen
        self.banner_due: float | None = None
        self.buf = bytearray()
        self.stat = STOP
        self.expected = 0
        self.received = 0  # G-code lines of the current job
        self.total_lines = 0  # every line, since the last dump
        self.sched = "normal"  # how the process is scheduled (main() raises it)
        self.last_line_at = 0.0
        self.stop_due: float | None = None
        self.bangs: list[float] = []
        self.sr_times: list[tuple[int, float]] = []
        self.sr_plan: tuple[int, int, float, float] | None = None  # next k, count, period, due
        self.cmd_buf = b""
        self.running = True

    # --- the loop

    def serve(self) -> None:
        say("listening")
        poller = select.poll()
        poller.register(sys.stdin.fileno(), select.POLLIN)
        master_on = False
        while self.running:
            if self.attached and not master_on:
                poller.register(self.fd, select.POLLIN)
                master_on = True
            elif not self.attached and master_on:
                poller.unregister(self.fd)
                master_on = False
            timeout = self._timeout()
            events = poller.poll(None if timeout is None else max(timeout * 1000, 0))
            for fd, ev in events:
                if fd == self.fd:
                    if ev & select.POLLIN:
                        self._read()
                    elif ev & (select.POLLHUP | select.POLLERR):
                        self._detach()
                else:
                    self._command()
            self._timers()

    def _timeout(self) -> float | None:
        now = time.monotonic()
        deadlines = []
        if not self.attached:
            deadlines.append(now + ATTACH_POLL)
        if self.banner_due is not None:
            deadlines.append(self.banner_due)
        if self.sr_plan is not None:
            deadlines.append(self.sr_plan[3])
        if self.stat == RUN:
            deadlines.append(self.last_line_at + IDLE_STOP)
        if self.stop_due is not None:
            deadlines.append(self.stop_due)
        return None if not deadlines else min(deadlines) - now

    def _timers(self) -> None:
        now = time.monotonic()
        if not self.attached:
            probe = select.poll()
            probe.register(self.fd, select.POLLIN)
            if not any(ev & select.POLLHUP for _, ev in probe.poll(0)):
                self.attached = True
                self.flushed = False
                self.banner_due = now + BANNER_FALLBACK
            return
        if self.banner_due is not None and now >= self.banner_due:
            self._banner()
        if self.stop_due is not None and now >= self.stop_due:
            self.stop_due = None
            if self.stat == RUN:
                self._set_stat(STOP)
        if self.stat == RUN and now - self.last_line_at >= IDLE_STOP:
            self._set_stat(STOP)
        plan = self.sr_plan
        if plan is not None and now >= plan[3]:
            k, count, period, due = plan
            out = b'{"sr":{"posx":%d}}\n' % k
            self.sr_times.append((k, time.monotonic()))
            self._write(out)
            self.sr_plan = None if k >= count else (k + 1, count, period, due + period)

    def _banner(self) -> None:
        self.banner_due = None
        self.stat = STOP
        self.stop_due = None
        self.received = 0
        self.buf.clear()
        self._write(BANNER)
        say("opened")

    def _detach(self) -> None:
        self.attached = False
        self.banner_due = None
        self.buf.clear()
        self.sr_plan = None

    def _read(self) -> None:
        try:
            packet = os.read(self.fd, 65536)
        except BlockingIOError:
            return
        except OSError as exc:
            if exc.errno != errno.EIO:
                raise
            self._detach()
            return
        now = time.monotonic()
        if not packet:
            self._detach()
            return
        if packet[0] != 0:  # a status packet
            if packet[0] & FLUSH_BITS and not self.flushed:
                # The opener's flush threw away anything sent before (a fallback banner too).
                self.flushed = True
                self._banner()
            return
        self.buf += memoryview(packet)[1:]
        out: list[bytes] = []
        buf = self.buf
        start = 0
        while (end := buf.find(b"\n", start)) >= 0:
            line = bytes(buf[start:end])
            start = end + 1
            self._line(line, now, out)
        del buf[:start]
        if out:
            self._write(b"".join(out))

    def _line(self, line: bytes, now: float, out: list[bytes]) -> None:
        if not line:
            return
        if len(line) == 1 and line[0] in REALTIME:
            self._realtime(line[0], now, out)
            return
        self.total_lines += 1
        if line[:1] == b"{":
            out.append(self._json(line))
            return
        self.last_line_at = now
        if self.stat not in (RUN, HOLD):
            self.stat = RUN
            out.append(b'{"sr":{"stat":5}}\n')
        numbered = _LINE_NUMBER.match(line)  # jv 4 echoes the line's N word, as g2core does
        body = b'"n":%s' % numbered[1] if numbered and int(numbered[1]) else b""
        out.append(b'{"r":{%s},"f":[1,0,%d]}\n' % (body, len(line) + 1))
        self.received += 1
        if self.expected and self.received >= self.expected:
            self.expected = 0
            self.received = 0
            self.stop_due = now + STOP_DELAY

    def _json(self, line: bytes) -> bytes:
        try:
            obj = json.loads(line)
        except ValueError:
            obj = {}
        body: dict[str, Any] = {}
        if isinstance(obj, dict):
            for key, value in obj.items():
                if key == "sr":
                    body["sr"] = {"stat": self.stat}
                else:
                    body[key] = 0 if value is None else value
        answer = {"r": body, "f": [1, 0, len(line) + 2]}
        return json.dumps(answer, separators=(",", ":")).encode() + b"\n"

    def _realtime(self, char: int, now: float, out: list[bytes]) -> None:
        if char == ord("!"):
            self.bangs.append(now)
            if self.stat == RUN:
                self.stat = HOLD
                out.append(b'{"sr":{"stat":6}}\n')
        elif char == ord("~"):
            if self.stat == HOLD:
                self.stat = RUN
                self.last_line_at = now
                out.append(b'{"sr":{"stat":5}}\n')
        elif char == 0x04 or (char == ord("%") and self.stat == HOLD):
            self.stat = END if char == 0x04 else STOP
            self.expected = self.received = 0
            self.stop_due = None
            out.append(b'{"sr":{"stat":%d}}\n' % self.stat)

    def _set_stat(self, stat: int) -> None:
        self.stat = stat
        self.received = 0
        self._write(b'{"sr":{"stat":%d}}\n' % stat)

    def _write(self, data: bytes) -> None:
        if not self.attached:
            return
        view = memoryview(data)
        while view:
            try:
                n = os.write(self.fd, view)
            except BlockingIOError:
                select.select([], [self.fd], [], 0.01)
                continue
            except OSError:
                return  # the host just went; the next read or poll notices
            view = view[n:]

    # --- commands from the bench

    def _command(self) -> None:
        chunk = os.read(sys.stdin.fileno(), 4096)
        if not chunk:
            self.running = False
            return
        self.cmd_buf += chunk
        *lines, self.cmd_buf = self.cmd_buf.split(b"\n")
        for raw in lines:
            words = raw.decode().split()
            if not words:
                continue
            if words[0] == "expect":
                self.expected = int(words[1])
                self.received = 0
            elif words[0] == "sr":
                count, rate = int(words[1]), float(words[2])
                self.sr_plan = (1, count, 1.0 / rate, time.monotonic())
            elif words[0] == "dump":
                say(
                    json.dumps(
                        {
                            "bangs": self.bangs,
                            "sr": self.sr_times,
                            "lines": self.total_lines,
                            "sched": self.sched,
                        }
                    )
                )
                self.bangs, self.sr_times, self.total_lines = [], [], 0
            elif words[0] == "quit":
                self.running = False

    def close(self) -> None:
        os.close(self.fd)
        with contextlib.suppress(OSError):
            os.unlink(self.link)


def say(text: str) -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def _run_like_hardware() -> str:
    """SCHED_FIFO if allowed, else a higher nice priority: what this process got."""
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
        return "SCHED_FIFO 10"
    with contextlib.suppress(OSError):
        os.nice(-10)
        return "nice -10"
    return "normal (no privilege to raise it)"


def main() -> None:
    sched = _run_like_hardware()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--link", required=True, help="the symlink to create for the slave")
    args = parser.parse_args()
    controller = Controller(args.link)
    controller.sched = sched
    try:
        controller.serve()
    finally:
        controller.close()


if __name__ == "__main__":
    main()
