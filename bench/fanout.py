"""The notification fan-out alone: one encoded notification to N subscribers of a real socket.

    python -m bench.fanout [--subscribers 20] [--notifications 5000] [--per-pass 1]
                           [--repeats 5] [--event-loop uvloop|asyncio] [--profile]

P8 (bench/run.py) runs 20 subscribers on `status` and `job` beside four
lasers; what each notification costs the daemon there is hidden in the whole
daemon's CPU. This harness measures only that: a real `ApiServer` on a Unix
socket, N connections to it from a child process that reads everything (so
its reading is not counted), each connection's `Client` in a real
`Subscriptions` table, and `deliver_line` of one already-encoded status-sized
notification, `--per-pass` at a time, with a loop pass between (as a board's
report is one read). The figure is the daemon side's CPU (`time.process_time`:
the Python, the `send` syscalls) per notification, all subscribers included,
the best of `--repeats` runs. `--profile` prints cProfile's top functions
instead.

    python -m bench.fanout --console all|but-job|off [--dialect grbl|g2core] [--lines N]

The console's own cost a job line, as bench/perline.py measures the line's
path (a real engine and session, an in-process board, no I/O), with the
engine publishing its console as a subscriber asks: `all` (api.md's
default: every line and answer an event, each encoded as the notification),
`but-job` (`job_lines: false`: a running job's own lines and their plain
answers not made into events) or `off` (nobody listens). CPU a line, the
best of `--repeats` jobs.
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import pstats
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from hostd.api.methods.subscriptions import Subscriptions
from hostd.api.peer import AccessPolicy
from hostd.api.server import ApiServer
from hostd.logs import configure_logging

# About the size of a grbl status notification with its snapshot.
NOTIFICATION = (
    b'{"jsonrpc":"2.0","method":"status","params":{"machine":"laser1","report":'
    + b'{"stat":5,"posx":12.3,"posy":45.6},"snapshot":{'
    + b",".join(b'"k%d":%d' % (i, i) for i in range(60))
    + b"}}}"
)

READER = """
import selectors, socket, sys
path, n = sys.argv[1], int(sys.argv[2])
socks = []
for _ in range(n):
    s = socket.socket(socket.AF_UNIX)
    s.connect(path)
    s.setblocking(False)
    socks.append(s)
print("ready", flush=True)
sel = selectors.DefaultSelector()
for s in socks:
    sel.register(s, selectors.EVENT_READ)
total = 0
while socks:
    for key, _ in sel.select():
        data = key.fileobj.recv(1 << 16)
        if not data:
            sel.unregister(key.fileobj)
            socks.remove(key.fileobj)
        total += len(data)
print(total, flush=True)
"""


async def run(subscribers: int, notifications: int, per_pass: int, profile: bool) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        path = str(Path(tmp) / "fan.sock")
        server = ApiServer({}, policy=AccessPolicy.default())
        async with server:
            await server.start(path)
            reader = await asyncio.create_subprocess_exec(
                sys.executable,
                "-c",
                READER,
                path,
                str(subscribers),
                stdout=subprocess.PIPE,
            )
            assert reader.stdout is not None
            assert (await reader.stdout.readline()).strip() == b"ready"
            for _ in range(3000):  # the server admits the connections on its own tasks
                if len(server.clients) >= subscribers:
                    break
                await asyncio.sleep(0.01)
            subs = Subscriptions()
            for client in server.clients:
                subs.add(client, client.send_line, ["status"], None)
            profiler = cProfile.Profile() if profile else None
            start = time.process_time()
            if profiler is not None:
                profiler.enable()
            for i in range(notifications):
                subs.deliver_line("status", "laser1", NOTIFICATION)
                if (i + 1) % per_pass == 0:
                    await asyncio.sleep(0)
            await asyncio.sleep(0)
            if profiler is not None:
                profiler.disable()
            spent = time.process_time() - start
            for client in server.clients:
                client.close("done")
            await reader.wait()
            if profiler is not None:
                pstats.Stats(profiler).sort_stats("tottime").print_stats(15)
            return spent / notifications


async def console_job(dialect: str, lines: int, console: str) -> float:
    """bench.perline's job, its engine's console as `console` says; CPU seconds."""
    from bench.client import program
    from bench.perline import Board, _connect, config
    from hostd.api.methods.subscriptions import console_notification
    from hostd.link import Channel
    from hostd.machine.engine import Engine
    from hostd.machine.events import Console, EngineEvent
    from hostd.machine.stream import JobStream
    from hostd.protocol.program import program_lines

    sent: list[int] = [0]

    def listener(event: EngineEvent) -> None:
        if isinstance(event, Console):
            sent[0] += len(console_notification(event))

    engine = Engine(config(dialect), listener)
    board = Board(dialect)
    await _connect(engine, board)
    engine.console = console == "all"
    engine.console_but_job = console != "off"
    stream = JobStream(iter(program_lines(program(lines).splitlines())), 1, numbered=True)
    board.expected = lines
    cpu0 = time.process_time()
    engine.start_stream(stream)
    while not stream.done:
        answers = board.read()
        if not answers:
            engine.query_status()
            continue
        engine.link_lines(Channel.DATA, answers)
    cpu = time.process_time() - cpu0
    if stream.acked != lines:
        raise RuntimeError(f"{dialect}: {stream.acked} of {lines} acked")
    return cpu


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bench.fanout", description=__doc__.split("\n")[0])
    parser.add_argument("--subscribers", type=int, default=20)
    parser.add_argument("--notifications", type=int, default=5000)
    parser.add_argument("--per-pass", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--event-loop", choices=("uvloop", "asyncio"), default="uvloop")
    parser.add_argument("--profile", action="store_true")
    parser.add_argument("--console", choices=("all", "but-job", "off"))
    parser.add_argument("--dialect", choices=("g2core", "grbl"), default="grbl")
    parser.add_argument("--lines", type=int, default=20_000)
    args = parser.parse_args(argv)
    configure_logging("warning")
    if args.console is not None:
        runs = [
            asyncio.run(console_job(args.dialect, args.lines, args.console))
            for _ in range(args.repeats)
        ]
        sys.stdout.write(
            f"{args.dialect}, console {args.console}: "
            f"{min(runs) / args.lines * 1e6:.2f} us CPU a line (best of {args.repeats})\n"
        )
        return 0
    loop_factory = asyncio.new_event_loop
    if args.event_loop == "uvloop":
        import uvloop

        loop_factory = uvloop.new_event_loop
    best = float("inf")
    for _ in range(1 if args.profile else args.repeats):
        with asyncio.Runner(loop_factory=loop_factory) as runner:
            cost = runner.run(
                run(args.subscribers, args.notifications, args.per_pass, args.profile)
            )
        best = min(best, cost)
    sys.stdout.write(
        f"{args.subscribers} subscribers, {args.per_pass} a pass, {args.event_loop}: "
        f"{best * 1e6:.1f} us CPU a notification, "
        f"{best * 1e6 / args.subscribers:.2f} us a subscriber (best of {args.repeats})\n"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
