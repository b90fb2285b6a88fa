"""The per-line path alone: the engine, the session and the stream, with no I/O.

    python -m bench.perline [--lines 40000] [--dialect g2core|grbl|both] [--repeats 5]
                            [--profile] [--jobs N]

P5 measures the whole daemon (the pty, serialx, the kernel) on a machine that
is shared, so its figure moves 2x from run to run. This harness measures only
the Python a line costs, deterministically: a real `Engine`, with its
dialect's real session and a real `JobStream` over a job's lines (numbered,
as a `make` job's), writes into a recording link, and an in-process board
answers every line as the bench's instant controller does (g2core: `{"r":
{"n":N},"f":[1,0,C]}`, grbl: `ok`). Each read hands the engine every answer
the board owes, as a host that is slower than its board reads them. The
figure is CPU seconds (`time.process_time`) per 10,000 lines, the best of
`--repeats` jobs; `--profile` prints cProfile's calls a line and the top
functions instead. No syscall, no serialx, no event-loop wake-up is in it:
it is what the code changes, not what a user's machine shows (P5 is that).

On a shared machine CPU time moves 2x from run to run; instructions do not.
`--jobs N` runs N jobs of one file and prints nothing, for valgrind:

    valgrind --tool=cachegrind --cache-sim=no --cachegrind-out-file=/dev/null \
        python -m bench.perline --dialect g2core --lines 5000 --jobs 3

and the same with `--jobs 1`: the difference of the two `I refs`, divided by
10,000, is the instructions a line of the job path (the board's included),
the same to a few hundred from run to run.
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import json
import pstats
import re
import sys
import time
from collections import deque
from typing import Any, Protocol

from bench.client import program
from hostd.link import Channel
from hostd.logs import configure_logging
from hostd.machine.config import MachineConfig
from hostd.machine.engine import Engine, LinkState
from hostd.machine.stream import JobStream
from hostd.protocol.program import program_lines

_NUMBER = re.compile(rb"N(\d+)")
G2_BANNER = (
    b'{"r":{"fv":0.99,"fb":101.03,"hp":3,"hv":0,"id":"bench","msg":"SYSTEM READY"},"f":[1,0,0]}'
)
GRBL_LINES = {
    b"$I": [b"[VER:1.1h.20190830:]", b"[OPT:V,15,128]", b"ok"],
    b"$$": [b"$32=0", b"$110=500.000", b"$130=300.000", b"ok"],
    b"$N": [b"$N0=", b"$N1=", b"ok"],
    b"$G": [b"[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]", b"ok"],
}


class Board:
    """Answers whatever the engine writes, at once, as the instant controller does."""

    dual = False

    def __init__(self, dialect: str) -> None:
        self.dialect = dialect
        self.owed: deque[bytes] = deque()
        self.stat = 3  # g2core: PROGRAM_STOP; grbl: Idle
        self.expected = 0
        self.received = 0
        self.writes = 0

    # the Link's writing side, as the engine calls it
    def write_lines(self, lines: list[bytes], *, control: bool = False) -> bool:
        self.writes += 1
        for line in lines:
            self._line(line.rstrip(b"\n"))
        return True

    def hand_over(self) -> None:
        """No process at the other end to give the CPU to."""

    def write_realtime(self, data: bytes) -> bool:
        self.writes += 1
        byte = data[:1]
        if self.dialect == "grbl" and byte == b"?":
            state = b"Run" if self.expected else b"Idle"
            self.owed.append(b"<%s|MPos:0.000,0.000,0.000|Bf:15,127|FS:0,0>" % state)
        return True

    def _line(self, line: bytes) -> None:
        if self.dialect == "grbl":
            self.owed.extend(GRBL_LINES.get(line, [b"ok"]))
            if line[:1] not in (b"$", b""):
                self._counted()
            return
        if line[:1] == b"{":
            obj = json.loads(line)
            body = {
                k: ({"stat": self.stat} if k == "sr" else (0 if v is None else v))
                for k, v in obj.items()
            }
            self.owed.append(json.dumps({"r": body, "f": [1, 0, len(line) + 2]}).encode())
            return
        if self.stat != 5:
            self.stat = 5
            self.owed.append(b'{"sr":{"stat":5}}')
        numbered = _NUMBER.match(line)
        echo = b'"n":%s' % numbered[1] if numbered and int(numbered[1]) else b""
        self.owed.append(b'{"r":{%s},"f":[1,0,%d]}' % (echo, len(line) + 1))
        self._counted()

    def _counted(self) -> None:
        self.received += 1
        if self.expected and self.received >= self.expected:
            self.expected = self.received = 0
            self.stat = 3
            if self.dialect == "g2core":
                self.owed.append(b'{"sr":{"stat":3}}')

    def read(self) -> list[bytes]:
        owed = list(self.owed)
        self.owed.clear()
        return owed


def config(dialect: str) -> MachineConfig:
    values: dict[str, object] = {
        "id": "bench",
        "dialect": dialect,
        "data_port": "/dev/null",
        "auto_connect": False,
        "heartbeat": 1000.0,
        "status_interval": 1000.0,
    }
    return MachineConfig.model_validate(values)


class InProcessBoard(Protocol):
    """What `connect` needs of a board answered in-process (here, and the fast-path tests')."""

    dialect: str
    owed: deque[bytes]

    def read(self) -> list[bytes]: ...


def connect(engine: Engine, board: InProcessBoard) -> None:
    """The engine on a board answered in-process, through its dialect's handshake."""
    engine.link = board  # type: ignore[assignment]
    engine.link_state = LinkState.HANDSHAKE
    engine.session.open()
    engine._deliver()
    if board.dialect == "g2core":
        board.owed.append(G2_BANNER)
    else:
        board.owed.extend([b"", b"Grbl 1.1h ['$' for help]"])
    for _ in range(100):
        if engine.ready:
            return
        answers = board.read()
        if answers:
            engine.link_lines(Channel.DATA, answers)
        else:
            engine.query_status()
    raise RuntimeError(f"{board.dialect}: no handshake")


async def run_job(
    dialect: str,
    lines: int,
    profiler: cProfile.Profile | None = None,
    text: list[str] | None = None,
) -> float:
    """One job of `lines` lines (of `text`, if given): CPU seconds from its start to its end."""
    engine = Engine(config(dialect))
    board = Board(dialect)
    connect(engine, board)
    if text is None:
        text = program(lines).splitlines()
    stream = JobStream(iter(program_lines(text)), 1, numbered=True)
    board.expected = lines
    cpu0 = time.process_time()
    if profiler is not None:
        profiler.enable()
    engine.start_stream(stream)
    while not stream.done:
        answers = board.read()
        if not answers:
            engine.query_status()  # the job's end: a report says the board rests
            continue
        engine.link_lines(Channel.DATA, answers)
    if profiler is not None:
        profiler.disable()
    cpu = time.process_time() - cpu0
    result = stream.result.result()
    if result.end.value != "completed" or stream.acked != lines:
        raise RuntimeError(f"{dialect}: the job ended {result} with {stream.acked} of {lines}")
    return cpu


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bench.perline", description=__doc__)
    parser.add_argument("--lines", type=int, default=40_000)
    parser.add_argument("--dialect", choices=("g2core", "grbl", "both"), default="both")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--profile", action="store_true")
    parser.add_argument(
        "--jobs",
        type=int,
        default=0,
        help="run this many jobs of one file and print nothing: under valgrind, the "
        "instructions of N jobs less those of one are the job path's alone",
    )
    args = parser.parse_args(argv)
    configure_logging("info")  # as the daemon runs: no per-line debug record
    dialects = ("g2core", "grbl") if args.dialect == "both" else (args.dialect,)
    if args.jobs:
        text = program(args.lines).splitlines()
        for dialect in dialects:
            for _ in range(args.jobs):
                asyncio.run(run_job(dialect, args.lines, text=text))
        return 0
    for dialect in dialects:
        if args.profile:
            profiler = cProfile.Profile()
            asyncio.run(run_job(dialect, args.lines, profiler))
            stats = pstats.Stats(profiler)
            calls: Any = stats.total_calls  # type: ignore[attr-defined]
            sys.stdout.write(f"{dialect}: {calls / args.lines:.1f} calls a line\n")
            stats.sort_stats("tottime").print_stats(25)
            continue
        runs = [asyncio.run(run_job(dialect, args.lines)) for _ in range(args.repeats)]
        per = [r / args.lines * 10_000 for r in runs]
        sys.stdout.write(
            f"{dialect}: {min(per):.4f} s per 10,000 lines (best of {len(per)}; "
            f"{', '.join(f'{p:.4f}' for p in per)}), {min(per) * 100:.1f} us a line\n"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
