"""P8's raw baseline: a bare host in the same cgroup, against the same rastering boards.

    python -m bench.rawp8 --dialect grbl --lines N [--window 4] LINK [LINK ...]

P8 asks whether a daemon held to a quarter of one core keeps four grbl lasers
(1,000 lines/s each) or two g2core boards (2,000 lines/s each) fed. What it
pays a line there is mostly what this machine charges a process for waking
up, not what hostd's Python does (docs/performance-log.md, "P8's floor: a bare
host in the same cgroup"). So P8 measures, in the same run, the least any
host of this shape could pay: this program, which does nothing but stream.

It is the daemon's way of streaming with everything else taken out: uvloop
and serialx as the daemon uses them (one protocol a port, a read per
wake-up, the port opened as hostd/link/serial.py opens it), the job's lines
encoded beforehand as the daemon encodes them (bench/raw.py `wire_lines`:
numbered on g2core, as they are on grbl), and the same flow control: on grbl
character counting against the 127 bytes a 128-byte receive ring holds (an
`ok` frees its line's bytes), on g2core a window of lines unanswered (a
`{"r":` frees one). Answers are counted, not parsed: no status, no
notifications, no job record.

As a process (the bench's use): it opens every port, waits for each board's
banner, prints `ready`; `go` on stdin starts the streams; it prints one JSON
line (`{"acked": [...], "sent": [...]}`, per port) when every line is
answered or when stdin says `stop` (or closes), and exits. The bench moves it
into its cgroup between `ready` and `go` and reads its CPU from /proc, as it
does the daemon's (`bare_window`).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench.cgroup import cpu_limit
from bench.client import raster
from bench.procs import ControllerProcess
from bench.raw import GRBL_ROOM, wire_lines

CLK_TCK = os.sysconf("SC_CLK_TCK")
BAUD = 115200  # what the daemon's config asks for (a pty ignores it)
# What each board writes when a host opens its port, up to the end of which the host waits.
BANNERS = {"grbl": b"['$' for help]\r\n", "g2core": b'"msg":"SYSTEM READY"'}
ANSWERS = {"grbl": b"ok\r\n", "g2core": b'{"r":'}  # one a line answered
FILL = 1.0  # s from `go` to the window: the planners filled (as P8 waits for the daemon's)
OPEN_TIMEOUT = 30.0  # s for the helper to open its ports and see every banner


class Port(asyncio.Protocol):
    """One board's stream: its lines, its flow control and its count of answers."""

    def __init__(self, dialect: str, lines: list[bytes], window: int) -> None:
        self.grbl = dialect == "grbl"
        self.lines = lines
        self.window = window
        self.banner = BANNERS[dialect]
        self.answer = ANSWERS[dialect]
        self.seen = b""  # before the stream: what came, until the banner
        self.pending = b""  # during it: a line not yet complete
        self.sent = self.acked = 0
        self.used = 0  # grbl: bytes written and not yet answered
        self.streaming = False
        loop = asyncio.get_running_loop()
        self.opened: asyncio.Future[None] = loop.create_future()
        self.done: asyncio.Future[None] = loop.create_future()
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport

    def connection_lost(self, exc: Exception | None) -> None:
        for future in (self.opened, self.done):
            if not future.done():
                future.set_exception(ConnectionError(f"the port closed: {exc}"))

    def start(self) -> None:
        self.streaming = True
        self.pending = self.seen  # anything after the banner (nothing, from these boards)
        if not self.lines:
            self.done.set_result(None)
            return
        self._pump()

    def _pump(self) -> None:
        """Write what the flow control lets through, in one write."""
        assert self.transport is not None
        lines, sent = self.lines, self.sent
        if self.grbl:
            end, used = sent, self.used
            while end < len(lines) and used + len(lines[end]) <= GRBL_ROOM:
                used += len(lines[end])
                end += 1
            self.used = used
        else:
            end = min(self.acked + self.window, len(lines))
        if end > sent:
            self.transport.write(b"".join(lines[sent:end]))
            self.sent = end

    def data_received(self, data: bytes) -> None:
        if not self.streaming:
            self.seen += data
            if not self.opened.done() and self.banner in self.seen:
                # From here on only answers to this stream count: drop the banner's line.
                rest = self.seen.split(self.banner, 1)[1]
                self.seen = rest.split(b"\n", 1)[1] if b"\n" in rest else b""
                self.opened.set_result(None)
            return
        data = self.pending + data
        cut = data.rfind(b"\n") + 1
        self.pending = data[cut:]
        answered = data.count(self.answer, 0, cut)
        if not answered:
            return
        if self.grbl:
            lines = self.lines
            self.used -= sum(len(lines[k]) for k in range(self.acked, self.acked + answered))
        self.acked += answered
        if self.acked >= len(self.lines):
            if not self.done.done():
                self.done.set_result(None)
        else:
            self._pump()


async def open_ports(links: list[str], dialect: str, lines: list[bytes], window: int) -> list[Port]:
    """Each link opened as the daemon opens a port, its board's banner read."""
    import serialx  # the daemon's serial library (hostd/link/serial.py)

    loop = asyncio.get_running_loop()
    ports = []
    for link in links:
        port = Port(dialect, lines, window)
        ports.append(port)
        await serialx.create_serial_connection(
            loop, lambda: ports[-1], url=link, baudrate=BAUD, exclusive=True
        )
    await asyncio.wait_for(asyncio.gather(*(p.opened for p in ports)), OPEN_TIMEOUT)
    return ports


async def run(ports: list[Port], stop: asyncio.Future[Any] | None = None) -> None:
    """Stream to every port at once until all its lines are answered (or `stop` is done)."""
    for port in ports:
        port.start()
    everything = asyncio.gather(*(p.done for p in ports))
    waits: list[asyncio.Future[Any]] = [everything]
    if stop is not None:
        waits.append(stop)
    await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
    if everything.done():
        everything.result()  # a port that closed says so
        return
    everything.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await everything


def close(ports: list[Port]) -> None:
    for port in ports:
        if port.transport is not None:
            port.transport.close()


async def stream(links: list[str], dialect: str, lines: list[bytes], window: int = 4) -> list[Port]:
    """Open every link and stream `lines` to each at once until all are answered."""
    ports = await open_ports(links, dialect, lines, window)
    try:
        await run(ports)
    finally:
        close(ports)
    return ports


# --- the helper process -------------------------------------------------------------------


async def _serve(links: list[str], dialect: str, lines: list[bytes], window: int) -> None:
    loop = asyncio.get_running_loop()
    commands: asyncio.Queue[str] = asyncio.Queue()
    buffered = b""

    def on_stdin() -> None:  # a reader on the loop, not a thread: the cgroup takes it all
        nonlocal buffered
        chunk = os.read(0, 4096)
        if not chunk:
            commands.put_nowait("stop")
            loop.remove_reader(0)
            return
        buffered += chunk
        *complete, buffered = buffered.split(b"\n")
        for line in complete:
            commands.put_nowait(line.decode().strip())

    loop.add_reader(0, on_stdin)

    async def until(word: str) -> None:
        while await commands.get() not in (word, "stop"):
            pass

    ports = await open_ports(links, dialect, lines, window)
    _say("ready")
    await until("go")
    stop = asyncio.ensure_future(until("stop"))
    try:
        await run(ports, stop)
    finally:
        stop.cancel()
        close(ports)
    _say(json.dumps({"acked": [p.acked for p in ports], "sent": [p.sent for p in ports]}))


def _say(text: str) -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dialect", choices=("g2core", "grbl"), required=True)
    parser.add_argument("--lines", type=int, required=True, help="raster lines a board")
    parser.add_argument("--window", type=int, default=4, help="g2core: lines unanswered")
    parser.add_argument("links", nargs="+")
    args = parser.parse_args()
    import uvloop  # as the daemon runs by default

    lines = wire_lines(raster(args.lines), args.dialect)
    _raise_mmap_threshold()
    uvloop.run(_serve(args.links, args.dialect, lines, args.window))


def _raise_mmap_threshold() -> None:
    """Have glibc serve serialx's read buffers from its heap, as the daemon's are.

    serialx reads with a 256 KiB buffer (descriptor_transport.py `max_size`), which
    CPython then shrinks to what came. glibc serves a block above its mmap threshold
    (128 KiB at start) with an mmap of its own, and raises the threshold to the size
    of any such block freed. A process that has not yet freed one larger than the read
    buffer pays an mmap, an mremap and a munmap on every read (strace -c). This helper
    did on grbl in `--quick`, whose job text (under 256 KiB) was the largest block it
    had freed: 61-62 us a line at a quarter core, throttled in 3 periods of 4, against
    37-41 us and no throttling with this (two runs each, alternated). On g2core its
    longer job had raised the threshold already; the daemon, its own raised long
    before, makes no such calls. A block of 1 MiB, allocated and freed here, puts every
    run on the daemon's footing, whatever the job's length.
    """
    bytes(1 << 20)


# --- the bench's side -----------------------------------------------------------------------


@dataclass
class HostWindow:
    """What a host did in one window of P8's length: the bare host's (`bare_window`), and
    the daemon's (`BudgetWindow` in run.py, which adds its holds)."""

    records: list[dict[str, Any]]  # each board's dump (bench/instant_controller.py)
    seconds: float
    cpu: float  # the host's CPU seconds (utime + stime) in the window
    periods: int  # the cgroup's CFS periods in the window, and those it was throttled in
    throttles: int
    throttled: float  # seconds

    @property
    def lines(self) -> int:
        return sum(record["job"]["lines"] for record in self.records)

    @property
    def rates(self) -> list[float]:
        return [record["job"]["lines"] / self.seconds for record in self.records]

    @property
    def gaps(self) -> list[float]:
        """Each time a board's planner ran empty mid-job, how long (s)."""
        return [gap for record in self.records for _, gap in record["starved"]]

    @property
    def overflows(self) -> int:
        """Bytes past the boards' receive buffers (grbl's; a g2core board's dump says 0)."""
        return sum(record["overflows"] for record in self.records)

    @property
    def late(self) -> float:
        """The most a board's own process woke after a block freed (s)."""
        return max(record["late"] for record in self.records)

    @property
    def credited(self) -> tuple[int, float]:
        """Reads whose first line got the time its input woke its board's process, and
        the most taken off such a line's arrival (s): the boards' own waits for a CPU."""
        return (
            sum(record.get("credited", 0) for record in self.records),
            max([0.0, *(record.get("credited_most", 0.0) for record in self.records)]),
        )

    @property
    def us_a_line(self) -> float:
        return self.cpu / max(self.lines, 1) * 1e6


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process (not its children), from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def bare_window(
    workdir: Path,
    dialect: str,
    count: int,
    rate: float,
    seconds: float,
    share: float,
    period_us: int,
    *,
    fifo: bool = False,
    cpus: set[int] | None = None,
) -> HostWindow:
    """The bare host on `count` fresh boards of `dialect` rastering at `rate`, in a cgroup
    of `share` of one core: started, given FILL s for the planners to fill, then measured
    for `seconds` (P8's window), as P8 measures the daemon. Needs root (the cgroup)."""
    window = 4  # the daemon's (bench/run.py WINDOW); grbl counts characters instead
    lines = round(rate * (FILL + seconds + 10))  # outlasts the window: stopped after it
    boards: list[ControllerProcess] = []
    host: subprocess.Popen[str] | None = None
    try:
        for i in range(count):
            link = str(workdir / f"ttyBARE{i}")
            boards.append(ControllerProcess(link, dialect, rate=rate, fifo=fifo))
        for board in boards:
            board.expect(lines)
        with cpu_limit(share, period_us) as limit:
            host = subprocess.Popen(
                [sys.executable, "-m", "bench.rawp8", "--dialect", dialect]
                + ["--lines", str(lines), "--window", str(window)]
                + [board.link for board in boards],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                text=True,
            )
            assert host.stdin is not None and host.stdout is not None
            said = host.stdout.readline().strip()
            if said != "ready":
                raise RuntimeError(f"bench.rawp8 did not open its ports: {said!r}")
            if cpus is not None:
                os.sched_setaffinity(host.pid, cpus)
            limit.enter(host.pid)  # from here on within the budget, as the daemon is
            host.stdin.write("go\n")
            host.stdin.flush()
            time.sleep(FILL)
            for board in boards:
                board.dump()
            stat0, cpu0, t0 = limit.stat(), cpu_seconds(host.pid), time.monotonic()
            throttled0 = limit.throttled_seconds()
            time.sleep(seconds)
            records = [board.dump() for board in boards]
            stat1, cpu1, t1 = limit.stat(), cpu_seconds(host.pid), time.monotonic()
            throttled1 = limit.throttled_seconds()
            host.stdin.write("stop\n")
            host.stdin.flush()
            result = json.loads(host.stdout.readline() or "{}")
            host.wait(10)
            if len(result.get("acked", [])) != count:
                raise RuntimeError(f"bench.rawp8 ended without its counts: {result!r}")
    finally:
        if host is not None and host.poll() is None:
            host.kill()
            host.wait()
        for board in boards:
            board.close()
    return HostWindow(
        records=records,
        seconds=t1 - t0,
        cpu=cpu1 - cpu0,
        periods=stat1.get("nr_periods", 0) - stat0.get("nr_periods", 0),
        throttles=stat1.get("nr_throttled", 0) - stat0.get("nr_throttled", 0),
        throttled=throttled1 - throttled0,
    )


if __name__ == "__main__":
    main()
