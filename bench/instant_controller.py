"""The bench's boards: a g2core or a grbl, answering each line as the firmware does.

    python -m bench.instant_controller --link PATH [--dialect grbl] [--rate 1000]

It sits on the master side of a pty pair whose slave is reachable through a
symlink (`--link`), like a /dev/serial/by-id link, so that a daemon (or the
raw baseline loop) opens it as a serial port. It is a separate process so
that what it costs is not charged to the host being measured.

Without `--rate` a board is "instant": it answers every line as soon as it
has read it, so the host alone sets the pace (P1, P2, P5, P6). With
`--rate R` it is a board rastering R short moves a second: a line is
answered when it enters a planner of `--blocks` blocks that runs one block
every 1/R s (bench/planner.py), which records every time the planner ran
empty mid-job because the next line had not arrived (P8).

g2core (the default), just enough for the daemon's handshake and jobs:

- The host's open ends with a tcflush, which discards anything written
  before it: the open is detected in pty packet mode (TIOCPKT), as the
  flush status packet, and only then is the SYSTEM READY banner written.
  While no host has the slave open the master polls POLLHUP; that is
  watched with a short poll, never with a blocking read.
- Every line gets one `{"r":...,"f":[1,0,N]}`: body `{"n":L}` for a line
  numbered `N<L>` with L > 0, as g2core at jv 4 (synthetos/g2
  g2core/json_parser.cpp:588, a line number is echoed when
  `echo_json_linenum`, set for jv >= 4 at :683, and the number is not 0),
  else `{}`; N: the line's length + 1, + 2 for a `{`-line (the terminator
  is counted, docs of /work/shared/spec/g2core.md section 2). A GET of `sr`
  (`{"sr":null}`, which is also what the daemon makes of `?` and
  `{"sr":n}`) is answered with the current `stat`, a GET of any other key
  with 0 (`{"r":{"xvm":0},"f":[1,0,13]}`); SETs are echoed.
- The first G-code line of a job sends `{"sr":{"stat":5}}`; the expected
  number of lines (`expect N` on stdin; the report follows 10 ms after the
  last line's answer, or when the planner has run the last block), or
  without one a short idle (0.2 s), `{"sr":{"stat":3}}`. A planner that runs empty mid-job is
  recorded, not reported (a g2core would report stat 3 and the daemon
  would raise its underflow fault): the bench reads the record.
- Realtime bytes: `!` (its arrival time is recorded with time.monotonic(),
  which is CLOCK_MONOTONIC and shared with the host on the same machine)
  holds (stat 6), `~` resumes (stat 5), 0x04 and `%` in a hold end the job
  (stat 4 / 3).

grbl (`--dialect grbl`, grbl 1.1h as gnea/grbl prints it):

- The banner `Grbl 1.1h ['$' for help]` after the host's tcflush
  (report.c:172); every answer ends in CRLF.
- Realtime bytes are picked out of the stream wherever they are and take
  no room (serial.c:143-170, the receive interrupt): `?` is answered at once with a
  status report `<Idle|MPos:...|Bf:15,127|FS:0,0>` (report.c:466-560,
  with `$10=3`: machine position and buffer state), `!` holds (Hold:0),
  `~` resumes, 0x18 resets (the banner again).
- Every other byte goes to a receive buffer of 128 bytes (serial.h:27, a
  ring that holds 127); a host that sends more than it holds overflows it,
  which is counted (`overflows`): character counting must never let it.
- Every line is answered `ok` (report.c:116), a motion line once it is in
  the planner (15 blocks, `[OPT:V,15,128]`: planner.h:31, BLOCK_BUFFER_SIZE
  16 less the one grbl keeps free, report.c:444); `$I`, `$$` and `$G`
  with what grbl prints for them.

Commands, one a line on stdin; answers on stdout:

- `expect N`: the next job has N lines.
- `sr COUNT RATE`: write `{"sr":{"posx":k}}` for k = 1..COUNT at RATE per
  second, recording the time just before each write (g2core).
- `dump`: one JSON line `{"bangs": [t, ...], "sr": [[k, t], ...], "lines": n,
  "sched": how it is scheduled, "job": {...}, "starved": [[t, s], ...],
  "overflows": n, "late": s, "rescued": n}`, then forget them. `job`: the
  G-code lines of the job read since the last dump and the times of the first
  and last; `starved`: each time the planner ran empty mid-job (when, for how
  long); `late`: the most this process woke after a block freed (its own
  delay); `rescued`: how often the safety net (`WAITING_LOOK`) found lines it
  should have planned already (0 unless this file has a bug); `unanswered`
  (g2core): the most G-code lines the board had read and not yet answered,
  counted as each read came in (answers the same read gets are not yet
  written): a host that keeps its window of N lines never makes it more than N;
  `credited`: reads whose first line was given the time its input woke this
  process, not the later time this process got a CPU to read it (`woken_at`),
  and `credited_most`, the most taken off such a line's arrival (s).
- `quit`.

A board is hardware of its own, but this process is not: by default it is
scheduled like any other process, as the rest of the bench is (the
headline figures are taken as on a user's computer). `--fifo` asks for
SCHED_FIFO (priority 10) so that it is never kept waiting behind the
bench's clients; the bench's `--pin` uses it, and its figures say so.

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
import threading
import time
import tty
from collections import deque
from typing import Any, TextIO

from bench.planner import Planner

BANNER = (
    b'{"r":{"fv":0.99,"fb":101.06,"hp":"bench","hv":"bench","id":"bench",'
    b'"msg":"SYSTEM READY"},"f":[1,0,1]}\n'
)
FLUSH_BITS = 0x01 | 0x02  # TIOCPKT_FLUSHREAD | TIOCPKT_FLUSHWRITE
ATTACH_POLL = 0.001  # s between looks for a host while none has the port open
BANNER_FALLBACK = 0.05  # s: a host that opens without a tcflush still gets its banner
# s: the longest the process sleeps while lines wait for a block. A safety net only, in
# addition to the deadlines (a block's free time, or "at once" when one is free): a board
# that slept through its deadlines once stalled a P8 window (docs/performance-log.md, "The
# bench's boards blocked in a read of the port"). A wake that finds lines it should have
# planned earlier is counted (`rescued` in the dump): that is a bug here, not the host.
WAITING_LOOK = 0.05
IDLE_STOP = 0.2  # s without a G-code line while running: the job is over
# s from the job's last line to its stop report: a board reports the stop once the last
# move has run, well after answering the line (and the daemon checks for an underflow
# if a stop comes while it still has lines to send).
STOP_DELAY = 0.01
# g2core's planner: 48 blocks (PLANNER_QUEUE_SIZE), and a data line is read only while 4
# are free (PLANNER_BUFFER_HEADROOM): 44 lines ahead (/work/shared/spec/g2core.md 6, 7.1).
G2CORE_BLOCKS = 44

STOP, END, RUN, HOLD = 3, 4, 5, 6
REALTIME = frozenset(b"!~%\x04\x18\x05")
_LINE_NUMBER = re.compile(rb"[Nn]([0-9]+)")


def woken_at(
    only_port: bool,
    deadline: float | None,
    before: tuple[int, int, int],
    after: tuple[int, int, int],
    now: float,
) -> float | None:
    """When the port's input woke this process in a `poll`, if that can be told; else None.

    `before` and `after` are the thread's schedstat (time run and time waited on a run
    queue, in ns; time slices) just before and just after the `poll`; `now` is read after
    `after`. A process waits on a run queue only between a wake-up and its next time
    slice, so when it slept once (one time slice more: it was not put off the CPU before
    it slept, nor after it woke, since a second slice would count the wait of either) the
    wait is all between the wake-up and the `poll`'s return, and `now` less that wait is no
    earlier than the wake-up. The wake-up was the port's when the port alone was ready and
    it came before the `poll`'s deadline (else the timeout may have woken it, and the input
    come during the wait). Stolen time of a virtual machine is no wait on a run queue: it
    stays in the line's arrival, against the host.
    """
    waited = after[1] - before[1]
    if not only_port or after[2] - before[2] != 1 or waited <= 0:
        return None  # (no wait: the line's time is its read's, as for any other)
    woke = now - waited / 1e9
    if deadline is not None and woke >= deadline:
        return None
    return woke


class RunQueue:
    """This thread's schedstat (`/proc/thread-self/schedstat`), read with one `pread`: the
    file is opened again when another thread asks (a test turns the loop in threads, and
    the file of a thread that has ended reads ESRCH)."""

    def __init__(self) -> None:
        self._fd: int | None = None
        self._thread = 0

    def read(self) -> tuple[int, int, int]:
        thread = threading.get_native_id()
        if self._fd is None or thread != self._thread:
            self._open(thread)
        assert self._fd is not None
        try:
            data = os.pread(self._fd, 128, 0)
        except ProcessLookupError:  # the thread it was opened in has ended (its id reused)
            self._open(thread)
            data = os.pread(self._fd, 128, 0)
        ran, waited, slices = data.split()[:3]
        return int(ran), int(waited), int(slices)

    def _open(self, thread: int) -> None:
        self.close()
        self._fd = os.open("/proc/thread-self/schedstat", os.O_RDONLY)
        self._thread = thread

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


class Controller:
    """The g2core; GrblController below changes what the lines and the realtime bytes do."""

    dialect = "g2core"
    default_blocks = G2CORE_BLOCKS

    def __init__(self, link: str, rate: float = 0.0, blocks: int | None = None) -> None:
        self.link = link
        master, slave = os.openpty()
        tty.setraw(slave)
        name = os.ttyname(slave)
        os.close(slave)  # while we hold a slave fd the master never sees the host go
        fcntl.ioctl(master, termios.TIOCPKT, struct.pack("i", 1))
        # Non-blocking: a `dump` reads the port itself (below), so a POLLIN the loop then
        # handles may find nothing left; a blocking read there slept until the host wrote
        # again, and a host whose window was full of lines waiting here never did.
        os.set_blocking(master, False)
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
        self.sched = "normal"  # how the process is scheduled (main() may raise it)
        self.last_line_at = 0.0
        self.stop_due: float | None = None
        self.bangs: list[float] = []
        self.sr_times: list[tuple[int, float]] = []
        self.sr_plan: tuple[int, int, float, float] | None = None  # next k, count, period, due
        self.cmd_buf = b""
        self.running = True
        # A rastering board (rate > 0): lines wait here, in order, for a planner block.
        self.planner = Planner(blocks or self.default_blocks, 1.0 / rate) if rate > 0 else None
        self.waiting: deque[tuple[bytes, float]] = deque()  # (line, when it was read)
        self.job_lines = 0  # G-code lines of jobs since the last dump, first and last read
        self.job_first: float | None = None
        self.job_last: float | None = None
        self.late = 0.0  # the most this process woke after a block freed
        self.rescued = 0  # wakes of the safety net (WAITING_LOOK) that planned lines
        # When the port's input woke this process for the read under way (`woken_at`):
        # the read's first line arrived then, not when the process got a CPU to read it.
        # A board is hardware of its own; this process waits for a CPU behind the bench's
        # clients, and a line it reads late would make the host look late (P8).
        self._woke: float | None = None
        self._run_queue = RunQueue()
        self.credited = 0  # reads whose first line got its wake-up's time
        self.credited_most = 0.0  # the most taken off such a line's arrival, s
        self.most_unanswered = 0  # G-code lines read, not answered (g2core), since the dump
        # The bench's commands and this process's answers (stdin and stdout; a test may
        # drive the loop with `step` and its own pipe).
        self.commands = 0  # stdin
        self.answers: TextIO = sys.stdout
        self._poller: select.poll | None = None
        self._master_on = False  # the port is registered in the poller

    # --- the loop

    def serve(self) -> None:
        self._say("listening")
        while self.running:
            self.step()

    def step(self, limit: float | None = None) -> None:
        """One turn of the loop: sleep until an input, the next deadline or the safety net
        (or `limit` seconds: a test's turn), take what came (the bench's commands first:
        poll lists them first), then run what is due."""
        poller = self._poller
        if poller is None:
            poller = self._poller = select.poll()
            poller.register(self.commands, select.POLLIN)
        if self.attached and not self._master_on:
            poller.register(self.fd, select.POLLIN)
            self._master_on = True
        elif not self.attached and self._master_on:
            poller.unregister(self.fd)
            self._master_on = False
        due = self._due()
        now = time.monotonic()
        wakes = [] if due is None else [due]
        if self.waiting and self.attached:
            wakes.append(now + WAITING_LOOK)  # the safety net, never the plan
        if limit is not None:
            wakes.append(now + limit)
        deadline = min(wakes) if wakes else None
        timeout = None if deadline is None else max((deadline - time.monotonic()) * 1000, 0)
        before = self._run_queue.read()
        events = poller.poll(timeout)
        after = self._run_queue.read()
        only_port = len(events) == 1 and events[0][0] == self.fd and events[0][1] == select.POLLIN
        self._woke = woken_at(only_port, deadline, before, after, time.monotonic())
        for fd, ev in events:
            if fd == self.fd:
                if ev & select.POLLIN:
                    self._read()
                elif ev & (select.POLLHUP | select.POLLERR):
                    self._detach()
            else:
                self._command()
        self._woke = None
        planned = self.job_lines
        self._timers()
        if self.job_lines > planned and not events and (due is None or time.monotonic() < due):
            # Lines planned by a wake that neither an input nor a deadline made (the net, or
            # a test's `limit`): no deadline had said a block would be free by now.
            self.rescued += 1

    def _deadlines(self) -> list[float]:
        now = time.monotonic()
        deadlines = []
        if not self.attached:
            deadlines.append(now + ATTACH_POLL)
        if self.banner_due is not None:
            deadlines.append(self.banner_due)
        if self.sr_plan is not None:
            deadlines.append(self.sr_plan[3])
        if self.stat == RUN and self._idle_stop():
            deadlines.append(self.last_line_at + IDLE_STOP)
        if self.stop_due is not None:
            deadlines.append(self.stop_due)
        if self.waiting and self.planner is not None:
            free = self.planner.next_free_wall(now)
            if free is not None:
                deadlines.append(free)
            elif self.planner.held_since is None:
                # A block freed since `_timers` planned what it could (its `now` is a little
                # older than this one): plan the waiting lines now. Without this the process
                # slept until its next input, which the host, its window full of these very
                # lines, never sent: a stall of seconds, counted as starvation (P8 g2core).
                deadlines.append(now)
        return deadlines

    def _due(self) -> float | None:
        """The next deadline (monotonic time), if any."""
        deadlines = self._deadlines()
        return min(deadlines) if deadlines else None

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
        if self.waiting:
            out: list[bytes] = []
            self._plan_waiting(now, out)
            if out:
                self._write(b"".join(out))
        if self.stop_due is not None and now >= self.stop_due:
            self.stop_due = None
            if self.stat == RUN:
                self._set_stat(STOP)
        if self.stat == RUN and self._idle_stop() and now - self.last_line_at >= IDLE_STOP:
            self._set_stat(STOP)
        plan = self.sr_plan
        if plan is not None and now >= plan[3]:
            k, count, period, due = plan
            out_sr = b'{"sr":{"posx":%d}}\n' % k
            self.sr_times.append((k, time.monotonic()))
            self._write(out_sr)
            self.sr_plan = None if k >= count else (k + 1, count, period, due + period)

    def _idle_stop(self) -> bool:
        """A lull in the lines ends a job, unless the board was told how long it is: then
        its end is its last line, and a host late mid-job is not turned into a stop (the
        daemon would take it for an underflow and end the run); a rastering board records
        running dry instead."""
        return not self.expected

    def _busy(self, now: float) -> bool:
        """Moving: blocks in the planner, or lines waiting for one."""
        return bool(self.waiting) or (self.planner is not None and self.planner.busy(now))

    def _banner(self) -> None:
        self.banner_due = None
        self._reset_board()
        self._write(BANNER)
        self._say("opened")

    def _reset_board(self) -> None:
        self.stat = STOP
        self.stop_due = None
        self.received = 0
        self.buf.clear()
        self.waiting.clear()
        if self.planner is not None:
            self.planner = Planner(self.planner.blocks, self.planner.period)

    def _detach(self) -> None:
        self.attached = False
        self.banner_due = None
        self.buf.clear()
        self.waiting.clear()
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
        out: list[bytes] = []
        self._data(memoryview(packet)[1:], now, out)
        self._woke = None  # a read that ended no line: the next one's came later
        if out:
            self._write(b"".join(out))

    def _data(self, data: memoryview, now: float, out: list[bytes]) -> None:
        self.buf += data
        buf = self.buf
        start = 0
        # Every G-code line read before is answered (and written) or waiting for a block.
        before, read = len(self.waiting), self.job_lines + len(self.waiting)
        while (end := buf.find(b"\n", start)) >= 0:
            line = bytes(buf[start:end])
            start = end + 1
            self._line(line, now, out)
        del buf[:start]
        # What the host had unanswered when this read came: the answers it gets are
        # written after it (`out`), so lines planned in it still count.
        fresh = self.job_lines + len(self.waiting) - read
        self.most_unanswered = max(self.most_unanswered, before + fresh)

    def _arrived(self, woke: float | None, now: float) -> float:
        """A G-code line's arrival: the wake-up's time for a read's first line (`_woke`,
        taken by whatever line comes first), else when it was read. `woken_at` gives a
        time before its `poll` returned, so before `now`."""
        if woke is None:
            return now
        self.credited += 1
        self.credited_most = max(self.credited_most, now - woke)
        return woke

    def _line(self, line: bytes, now: float, out: list[bytes]) -> None:
        woke, self._woke = self._woke, None  # the read's first line alone came at the wake
        if not line:
            return
        if len(line) == 1 and line[0] in REALTIME:
            self._realtime(line[0], now, out)
            return
        self.total_lines += 1
        if line[:1] == b"{":
            out.append(self._json(line))  # a control: ahead of data lines still waiting
            return
        if line[:1] == b"$" and line[1:].isalnum():
            # A text-mode GET (`$stat`: the daemon's fence behind a ^D) is answered in JSON
            # in JSON mode, as g2core's text_parser.cpp:84-96 does: `{"r":{"stat":3},...}`.
            out.append(self._json(b'{"%s":null}' % line[1:], len(line) + 1))
            return
        self.last_line_at = now
        if self.stat not in (RUN, HOLD):
            self.stat = RUN
            out.append(b'{"sr":{"stat":5}}\n')
        if self.planner is None:
            self._gcode(line, now, now, out)
            return
        self.waiting.append((line, self._arrived(woke, now)))
        self._plan_waiting(now, out)

    def _plan_waiting(self, now: float, out: list[bytes]) -> None:
        """Lines that were waiting for a block take those that have freed, in order."""
        planner = self.planner
        assert planner is not None
        while self.waiting:
            if planner.queued(now) >= planner.blocks:
                return  # full (held or not): the next one waits for a block to run
            line, arrival = self.waiting.popleft()
            due = planner.to_wall(planner.recent[0]) if len(planner.recent) >= planner.blocks else 0
            if arrival < due:  # it waited for this block: did this process wake in time?
                self.late = max(self.late, now - due)
            self._gcode(line, arrival, now, out)

    def _gcode(self, line: bytes, arrival: float, now: float, out: list[bytes]) -> None:
        """A G-code line taken by the board: planned (if it models a planner) and answered."""
        self._job_line(arrival, now)
        numbered = _LINE_NUMBER.match(line)  # jv 4 echoes the line's N word, as g2core does
        body = b'"n":%s' % numbered[1] if numbered and int(numbered[1]) else b""
        out.append(b'{"r":{%s},"f":[1,0,%d]}\n' % (body, len(line) + 1))
        if self.expected and self.received >= self.expected:
            self.expected = 0
            self.received = 0
            end = now if self.planner is None else self.planner.to_wall(self.planner.last_done)
            self.stop_due = max(end, now) + STOP_DELAY

    def _job_line(self, arrival: float, now: float) -> None:
        """Book one G-code line of a job: the planner's block, the job's counts."""
        self.received += 1
        self.job_lines += 1
        if self.job_first is None:
            self.job_first = arrival
        self.job_last = arrival
        planner = self.planner
        if planner is not None:
            planner.add(arrival, now)
            if self.received == 1:
                planner.begin_job()
            if self.expected and self.received >= self.expected:
                planner.end_job()

    def _json(self, line: bytes, size: int | None = None) -> bytes:
        try:
            obj = json.loads(line)
        except ValueError:
            obj = {}
        body: dict[str, Any] = {}
        if isinstance(obj, dict):
            for key, value in obj.items():
                if key == "sr":
                    body["sr"] = {"stat": self.stat}
                elif key == "stat":
                    body["stat"] = self.stat
                else:
                    body[key] = 0 if value is None else value
        answer = {"r": body, "f": [1, 0, len(line) + 2 if size is None else size]}
        return json.dumps(answer, separators=(",", ":")).encode() + b"\n"

    def _realtime(self, char: int, now: float, out: list[bytes]) -> None:
        if char == ord("!"):
            self.bangs.append(now)
            if self.stat == RUN:
                self.stat = HOLD
                self._hold(now)
                out.append(b'{"sr":{"stat":6}}\n')
        elif char == ord("~"):
            if self.stat == HOLD:
                self.stat = RUN
                self.last_line_at = now
                self._resume(now, out)
                out.append(b'{"sr":{"stat":5}}\n')
        elif char == 0x04 or (char == ord("%") and self.stat == HOLD):
            self.stat = END if char == 0x04 else STOP
            self.expected = self.received = 0
            self.stop_due = None
            self.waiting.clear()
            if self.planner is not None:
                self.planner = Planner(self.planner.blocks, self.planner.period)
            out.append(b'{"sr":{"stat":%d}}\n' % self.stat)

    def _hold(self, now: float) -> None:
        if self.planner is not None:
            self.planner.hold(now)

    def _resume(self, now: float, out: list[bytes]) -> None:
        if self.planner is not None:
            self.planner.resume(now)
            if self.waiting:
                self._plan_waiting(now, out)

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
        chunk = os.read(self.commands, 4096)
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
                # What the host wrote before the bench asked is counted: the loop looks at
                # stdin ahead of the port, so a `!` written just before a dump was still
                # unread ("32 feedholds sent, 31 `!` received", once, in P8). The loop may
                # then find nothing left to read for the POLLIN it had: the port is
                # non-blocking for that.
                if self.attached and select.select([self.fd], [], [], 0)[0]:
                    self._read()
                self._say(json.dumps(self._records()))
                self._forget_records()
            elif words[0] == "quit":
                self.running = False

    def _records(self) -> dict[str, Any]:
        planner = self.planner
        return {
            "bangs": self.bangs,
            "sr": self.sr_times,
            "lines": self.total_lines,
            "sched": self.sched,
            "dialect": self.dialect,
            "job": {"lines": self.job_lines, "first": self.job_first, "last": self.job_last},
            "starved": [] if planner is None else [[s.at, s.seconds] for s in planner.starved],
            "overflows": 0,
            "late": self.late,
            "rescued": self.rescued,
            "credited": self.credited,
            "credited_most": self.credited_most,
            "unanswered": self.most_unanswered,
        }

    def _forget_records(self) -> None:
        self.bangs, self.sr_times, self.total_lines = [], [], 0
        self.job_lines, self.job_first, self.job_last = 0, None, None
        self.late = 0.0
        self.rescued = 0
        self.credited, self.credited_most = 0, 0.0
        self.most_unanswered = 0
        if self.planner is not None:
            self.planner.starved = []

    def _say(self, text: str) -> None:
        self.answers.write(text + "\n")
        self.answers.flush()

    def close(self) -> None:
        self._run_queue.close()
        os.close(self.fd)
        with contextlib.suppress(OSError):
            os.unlink(self.link)


# --- grbl ---------------------------------------------------------------------------------

GRBL_BANNER = b"\r\nGrbl 1.1h ['$' for help]\r\n"  # report.c:172
GRBL_RX = 128  # serial.h: RX_BUFFER_SIZE; the ring holds one byte less
GRBL_BLOCKS = 15  # planner.h BLOCK_BUFFER_SIZE 16, one kept free (report.c:444)
GRBL_BUILD = b"[VER:1.1h.20190830:]\r\n[OPT:V,15,128]\r\nok\r\n"
GRBL_MODES = b"[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]\r\nok\r\n"
# $$ as grbl 1.1h prints its defaults (settings.c, defaults.h), $10=3: MPos and Bf in reports,
# and $32=1: laser mode, as the lasers of P8 are set up.
GRBL_SETTINGS = (
    b"$0=10\r\n$1=25\r\n$2=0\r\n$3=0\r\n$4=0\r\n$5=0\r\n$6=0\r\n$10=3\r\n$11=0.010\r\n"
    b"$12=0.002\r\n$13=0\r\n$20=0\r\n$21=0\r\n$22=0\r\n$23=0\r\n$24=25.000\r\n"
    b"$25=500.000\r\n$26=250\r\n$27=1.000\r\n$30=1000\r\n$31=0\r\n$32=1\r\n"
    b"$100=250.000\r\n$101=250.000\r\n$102=250.000\r\n$110=6000.000\r\n$111=6000.000\r\n"
    b"$112=500.000\r\n$120=1000.000\r\n$121=1000.000\r\n$122=10.000\r\n"
    b"$130=300.000\r\n$131=200.000\r\n$132=50.000\r\nok\r\n"
)
OK = b"ok\r\n"
_GRBL_PICKED = re.compile(rb"[?!~\x18\x80-\xff]")  # and every byte over 0x7f (serial.c:156)


class GrblController(Controller):
    """grbl 1.1: `ok` per line, a 128-byte receive buffer, `?` answered with a report."""

    dialect = "grbl"
    default_blocks = GRBL_BLOCKS

    def __init__(self, link: str, rate: float = 0.0, blocks: int | None = None) -> None:
        super().__init__(link, rate, blocks)
        self.unanswered = 0  # bytes received and not answered: the host's count of them
        self.overflows = 0
        self.held = False
        self.job_active = False  # an instant board "moves" from a job's first line to its last

    def _banner(self) -> None:
        self.banner_due = None
        self._reset_board()
        self.unanswered = 0
        self.held = self.job_active = False
        self._write(GRBL_BANNER)
        self._say("opened")

    def _data(self, data: memoryview, now: float, out: list[bytes]) -> None:
        buf = self.buf
        chunk = bytes(data)
        if _GRBL_PICKED.search(chunk):  # rare: most reads hold none
            self._woke = None  # a realtime byte may have been what woke the process
            # Picked out as they arrive (the receive interrupt), ahead of the lines before them.
            for match in _GRBL_PICKED.finditer(chunk):
                self._grbl_realtime(match[0][0], now, out)
            chunk = _GRBL_PICKED.sub(b"", chunk)
        buf += chunk
        self.unanswered += len(chunk)
        if self.unanswered > GRBL_RX - 1:
            self.overflows += 1  # on a board the bytes past the buffer would be lost
        start = 0
        while (end := buf.find(b"\n", start)) >= 0:
            line = bytes(buf[start:end]).rstrip(b"\r")
            self._grbl_line(line, end + 1 - start, now, out)
            start = end + 1
        del buf[:start]

    def _grbl_line(self, line: bytes, size: int, now: float, out: list[bytes]) -> None:
        woke, self._woke = self._woke, None  # the read's first line alone came at the wake
        self.total_lines += 1
        if line[:1] == b"$" or not line:
            self.unanswered -= size
            out.append(self._system(line))
            return
        self.last_line_at = now
        if self.planner is None:
            self.unanswered -= size
            self._grbl_gcode(now, now, out)
            return
        self.waiting.append((line + b"\n", self._arrived(woke, now)))
        self._plan_waiting(now, out)

    def _plan_waiting(self, now: float, out: list[bytes]) -> None:
        planner = self.planner
        assert planner is not None
        while self.waiting:
            if planner.queued(now) >= planner.blocks:
                return
            line, arrival = self.waiting.popleft()
            due = planner.to_wall(planner.recent[0]) if len(planner.recent) >= planner.blocks else 0
            if arrival < due:
                self.late = max(self.late, now - due)
            self.unanswered -= len(line)
            self._grbl_gcode(arrival, now, out)

    def _grbl_gcode(self, arrival: float, now: float, out: list[bytes]) -> None:
        if not self.job_active:
            self.job_active = True
        self._job_line(arrival, now)
        out.append(OK)
        if self.expected and self.received >= self.expected:
            self.expected = self.received = 0
            self.job_active = False

    def _system(self, line: bytes) -> bytes:
        if line == b"$I":
            return GRBL_BUILD
        if line == b"$$":
            return GRBL_SETTINGS
        if line == b"$G":
            return GRBL_MODES
        if line == b"$N":  # gnea/grbl report.c report_startup_line, N_STARTUP_LINE 2
            return b"$N0=\r\n$N1=\r\nok\r\n"
        if line == b"$X":
            return b"[MSG:Caution: Unlocked]\r\nok\r\n"
        return OK

    def _state(self, now: float) -> str:
        if self.held:
            return "Hold:0"
        if self.planner is None:
            return "Run" if self.job_active else "Idle"
        return "Run" if self._busy(now) else "Idle"

    def _report(self, now: float) -> bytes:
        queued = 0 if self.planner is None else self.planner.queued(now)
        moving = self._state(now) == "Run"
        return b"<%s|MPos:0.000,0.000,0.000|Bf:%d,%d|FS:%d,0>\r\n" % (
            self._state(now).encode(),
            GRBL_BLOCKS - queued,
            max(GRBL_RX - 1 - self.unanswered, 0),
            1000 if moving else 0,
        )

    def _grbl_realtime(self, byte: int, now: float, out: list[bytes]) -> None:
        if byte == ord("?"):
            out.append(self._report(now))
        elif byte == ord("!"):
            self.bangs.append(now)
            if self._state(now) == "Run":
                self.held = True
                self._hold(now)
        elif byte == ord("~"):
            if self.held:
                self.held = False
                self._resume(now, out)
        elif byte == 0x18:
            self._banner_after_reset(out)

    def _resume(self, now: float, out: list[bytes]) -> None:
        if self.planner is not None:
            self.planner.resume(now)
            if self.waiting:
                self._plan_waiting(now, out)

    def _banner_after_reset(self, out: list[bytes]) -> None:
        self._reset_board()
        self.unanswered = 0
        self.held = self.job_active = False
        self.expected = 0
        out.append(GRBL_BANNER)

    def _timers(self) -> None:
        # grbl pushes no status and has no idle stop of its own: only the planner's times.
        now = time.monotonic()
        if not self.attached or self.banner_due is not None:
            super()._timers()
            return
        if self.waiting:
            out: list[bytes] = []
            self._plan_waiting(now, out)
            if out:
                self._write(b"".join(out))

    def _records(self) -> dict[str, Any]:
        records = super()._records()
        records["overflows"] = self.overflows
        del records["unanswered"]  # a host's grbl stream is bounded in bytes: `overflows`
        return records

    def _forget_records(self) -> None:
        super()._forget_records()
        self.overflows = 0


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
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--link", required=True, help="the symlink to create for the slave")
    parser.add_argument("--dialect", choices=("g2core", "grbl"), default="g2core")
    parser.add_argument(
        "--rate", type=float, default=0.0, help="blocks a second the planner runs (0: instant)"
    )
    parser.add_argument("--blocks", type=int, help="the planner's blocks (default: the board's)")
    parser.add_argument("--fifo", action="store_true", help="ask for SCHED_FIFO (pinned runs)")
    args = parser.parse_args()
    sched = _run_like_hardware() if args.fifo else "normal"
    kind = GrblController if args.dialect == "grbl" else Controller
    controller = kind(args.link, args.rate, args.blocks)
    controller.sched = sched
    try:
        controller.serve()
    finally:
        controller.close()


if __name__ == "__main__":
    main()
