"""The steady state's fast path (issue 30) does exactly what the general path does.

A read that holds only plain answers to a job's lines is taken in one pass
(`receive_plain`, `_take_answers`), the job's plain lines are taken and
booked together (`Stream.take_run`), and when those are all there is to
write the session takes the read and the lines in one call and the engine
writes them without its delivery loop (`Session.express`, `Engine._express`).
None may change a byte written, an event, or a count: here a real `Engine`
with each dialect's real session streams random jobs twice, fast path on
and off, against a board that answers the same way both times (the answers
split into reads at random, error answers, status reports in the middle of
a read, a pause (its `!`) and a resume between reads, hold points
released, on g2core bursts of client queries that fill the control lane),
and everything the two runs wrote, told and counted is compared. Both runs
also check, at every write, the rules that must never break: the window and
the receive buffer are never exceeded, no job line is written while the job
is paused, and a realtime byte leaves in the write of its own call, ahead of
any line.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import random
import re
from collections import deque
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bench.perline import connect
from hostd.link import Channel
from hostd.machine.config import MachineConfig
from hostd.machine.engine import Engine
from hostd.machine.events import EngineEvent
from hostd.machine.stream import JobStream
from hostd.protocol.program import program_lines
from hostd.protocol.states import MachineState
from hostd.protocol.stream import LOOK_AHEAD

GRBL_HANDSHAKE = {
    b"$I": [b"[VER:1.1h.20190830:]", b"[OPT:V,15,128]", b"ok"],
    b"$$": [b"$32=0", b"ok"],
    b"$N": [b"$N0=", b"$N1=", b"ok"],
    b"$G": [b"[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]", b"ok"],
}
_NUMBER = re.compile(rb"N(\d+)")
WINDOW = 4
CONTROL_LANE = 4  # g2core's control lines unanswered at once (linemode.CONTROL_WINDOW)
RX = 128

# Job lines: mostly plain moves, and every kind the fast path must leave to the general one.
PLAIN = ["G1 X1 Y2 F3000", "G0 X10", "G1 X1.5 Y-2.25 S100", "M3 S500", "G1 Z-0.1"]
SPECIAL = [
    "M0",  # a program pause: `program_pauses`
    "M1",
    "G10 L20 P1 X0",  # grbl: may store (send-response)
    "G28.1",
    "G4 P0",
    "G1 X1e5",  # refused on the host: the job fails when its turn comes
    "$X",  # a `$` line in a job
    "M2",
    "M6 T1",  # a hold point: the job holds before it until released
]
G2_ONLY = ['{"sr":null}']  # a job's own JSON line: the control lane
GRBL_ONLY = ["$N", "$G"]  # views whose `ok` the general path reads in full (`$N`: startup blocks)


class Board:
    """Answers what the engine writes, with choices drawn from `rng` (the same both runs)."""

    def __init__(self, dialect: str, rng: random.Random, error_rate: float) -> None:
        self.dialect = dialect
        self.rng = rng
        self.error_rate = error_rate
        self.owed: deque[bytes] = deque()
        self.writes: list[tuple[str, bytes]] = []
        self.stat = 3
        self.paused = False  # the harness's pause: no job line may be written meanwhile
        self.data_unanswered = 0  # g2core: data lines written, not answered
        self.rx_used: deque[int] = deque()  # grbl: bytes of lines not answered
        self.dual = False

    # the Link's writing side
    def write_lines(self, lines: list[bytes], *, control: bool = False) -> bool:
        data = b"".join(lines)
        self.writes.append(("lines", data))
        for line in lines:
            assert line.endswith(b"\n") and b"\n" not in line[:-1]
            self._line(line[:-1])
        return True

    def hand_over(self) -> None:
        """No process at the other end to give the CPU to."""

    def write_realtime(self, data: bytes) -> bool:
        self.writes.append(("realtime", data))
        byte = data[:1]
        if self.dialect == "grbl":
            if byte == b"?":
                state = b"Run" if self.rx_used else b"Idle"
                free = 15 - min(len(self.rx_used), 15)
                self.owed.append(b"<%s|MPos:0.000,0.000,0.000|Bf:%d,127|FS:0,0>" % (state, free))
            elif byte == b"\x18":
                self.owed.clear()
                self.rx_used.clear()
                self.owed.extend([b"", b"Grbl 1.1h ['$' for help]"])
        elif byte == b"!":
            self.stat = 6
            self.owed.append(b'{"sr":{"stat":6}}')
        elif byte == b"~":
            self.stat = 5
            self.owed.append(b'{"sr":{"stat":5}}')
        elif byte in (b"\x04", b"%"):
            self.owed.clear()
            self.data_unanswered = 0
            self.stat = 4
            if byte == b"\x04":
                self.owed.append(b'{"er":{"fb":101.03,"st":207,"msg":"Job killed"}}')
            self.owed.append(b'{"sr":{"stat":4}}')
        return True

    def _line(self, line: bytes) -> None:
        rng = self.rng
        if self.dialect == "grbl":
            if line in GRBL_HANDSHAKE:
                self.owed.extend(GRBL_HANDSHAKE[line])
                return
            self.rx_used.append(len(line) + 1)
            assert sum(self.rx_used) <= RX - 1, "grbl's receive buffer overfilled"
            fail = line[:1] == b"N" and rng.random() < self.error_rate
            self.owed.append(b"error:20" if fail else b"ok")
            return
        if line[:1] == b"{":
            obj = json.loads(line)
            if "sr" in obj and self.stat == 5 and not self.data_unanswered:
                self.stat = 3  # everything answered: the board has come to rest
            body = {
                k: ({"stat": self.stat} if k == "sr" else (0 if v is None else v))
                for k, v in obj.items()
            }
            self.owed.append(json.dumps({"r": body, "f": [1, 0, len(line) + 2]}).encode())
            return
        if line == b"$stat":  # the fence behind a kill: a GET, answered as it is read
            self.owed.append(b'{"r":{"stat":%d},"f":[1,0,6]}' % self.stat)
            return
        self.data_unanswered += 1
        if self.stat == 3:
            self.stat = 5
            self.owed.append(b'{"sr":{"stat":5}}')
        assert self.data_unanswered <= WINDOW + 1, "g2core's window exceeded"
        numbered = _NUMBER.match(line)
        echo = b'"n":%s' % numbered[1] if numbered and int(numbered[1]) else b""
        status = 108 if numbered and rng.random() < self.error_rate else 0
        self.owed.append(b'{"r":{%s},"f":[1,%d,%d]}' % (echo, status, len(line) + 1))

    def read(self) -> list[bytes]:
        """Some of what the board owes, as one read: split, and with reports between."""
        rng = self.rng
        take = rng.randint(1, max(1, len(self.owed)))
        lines = [self.owed.popleft() for _ in range(min(take, len(self.owed)))]
        for line in lines:
            if self.dialect == "grbl":
                if line in (b"ok", b"error:20") and self.rx_used:
                    self.rx_used.popleft()
            elif (line.startswith(b'{"r":{') and b'"n"' in line) or line.startswith(b'{"r":{}'):
                self.data_unanswered = max(0, self.data_unanswered - 1)
        if lines and rng.random() < 0.3:  # a report in the middle of a read
            report = (
                b"<Run|MPos:1.000,0.000,0.000|Bf:10,100|FS:0,0>"
                if self.dialect == "grbl"
                else b'{"sr":{"stat":%d,"line":%d}}' % (self.stat, rng.randint(0, 40))
            )
            lines.insert(rng.randint(0, len(lines)), report)
        return lines


def _config(dialect: str) -> MachineConfig:
    return MachineConfig.model_validate(
        {
            "id": "t",
            "dialect": dialect,
            "data_port": "/dev/null",
            "auto_connect": False,
            "heartbeat": 1000.0,
            "status_interval": 1000.0,
        }
    )


def _connect(engine: Engine, board: Board) -> None:
    """The engine on the board, through the dialect's handshake; its writes forgotten."""
    connect(engine, board)
    board.writes.clear()


async def _run(
    dialect: str,
    fast: bool,
    job: list[str],
    seed: int,
    error_rate: float,
    listening: bool = False,
    status_traffic: bool = True,
    look_ahead: int = 8,
    queries: bool = True,
) -> Any:
    rng = random.Random(seed)
    events: list[str] = []

    def heard(event: EngineEvent) -> None:
        events.append(repr(event))

    engine = Engine(_config(dialect), heard)
    session = engine.session
    session.fast_path = fast
    # A console listener without the job's lines (the dashboard's `job_lines: false`):
    # every other line read or written is published, in order, among the events.
    engine.console_but_job = listening
    engine.console_status = status_traffic
    if listening and not fast:  # the reference: each line taken, then published, one by one
        engine._receive = lambda lines, channel: engine._receive_published(channel, lines)  # type: ignore[method-assign,assignment,misc]
    taken = 0
    plain = session._take_answers

    def counted(lines: list[bytes], start: int, stream: Any, *, whole: bool = False) -> int:
        nonlocal taken
        index = plain(lines, start, stream, whole=whole)
        taken += index - start
        return index

    session._take_answers = counted  # type: ignore[method-assign]
    express = 0
    due = session.express

    def counted_due(lines: list[bytes]) -> list[bytes] | None:
        nonlocal express
        written = due(lines)
        express += bool(written)  # a read taken whole, and the job's lines written at once
        return written

    session.express = counted_due  # type: ignore[method-assign]
    board = Board(dialect, rng, error_rate)
    _connect(engine, board)
    holds = {number for number, text in enumerate(job, 1) if text.startswith("M6")}
    # A look-ahead of 8: jobs of a few dozen lines still have a steady state to compare.
    stream = JobStream(
        iter(program_lines(job)), 1, numbered=True, holds=holds or None, look_ahead=look_ahead
    )
    engine.start_stream(stream)
    paused = False
    for _step in range(len(job) * 4 + 40):
        if stream.done:
            break
        roll = rng.random()
        if roll < 0.05 and not paused:
            before = len(board.writes)
            engine.pause_stream()
            paused = board.paused = True
            assert board.writes[before:] and board.writes[before][0] == "realtime"
            assert all(kind == "realtime" for kind, _ in board.writes[before:])
        elif roll < 0.10 and paused:
            paused = board.paused = False
            engine.resume_stream()
        elif roll < 0.40 and stream.held is not None:
            engine.release_stream()  # the tool change answered
        elif 0.40 <= roll < 0.43 and queries and dialect == "g2core":
            # Client queries, more than the control lane holds: the rest wait in it, and
            # the reads meanwhile are the general path's (`_pump` writes them first).
            for _ in range(CONTROL_LANE + 2):
                engine.session.send('{"sr":null}', engine._future())
            engine._deliver()
        answers = board.read()
        written = len(board.writes)
        if answers:
            engine.link_lines(Channel.DATA, answers)
        else:
            engine.query_status()
        if paused:  # not a job line while the job is paused
            assert not any(
                b"N" in data[:1] for kind, data in board.writes[written:] if kind == "lines"
            )
    position = stream.position
    # Copies: `asyncio.run` turns the loop once more on its way out, and a poll timer
    # (a hold's settle poll, 20 ms on) that came due during a slow run would write then.
    return {
        "taken": taken,
        "express": express,
        "writes": list(board.writes),
        "events": list(events),
        "counts": (
            position.sent,
            position.acked,
            position.rejected,
            position.discarded,
            position.last_acked_line,
            position.line_executed,
            (position.program_pauses, position.at_program_pause),
            position.done,
            str(position.result),
            session._lines_in,  # type: ignore[attr-defined]
            session.unanswered(),
            getattr(session, "_rx_used", None),
        ),
    }


def _jobs(extra: list[str]) -> st.SearchStrategy[list[str]]:
    plain = st.sampled_from(PLAIN)
    return st.lists(
        st.one_of(plain, plain, plain, st.sampled_from(SPECIAL + extra)), min_size=1, max_size=40
    )


def _compare(dialect: str, job: list[str], seed: int, error_rate: float, listening: bool) -> None:
    fast = asyncio.run(_run(dialect, True, job, seed, error_rate, listening))
    slow = asyncio.run(_run(dialect, False, job, seed, error_rate, listening))
    assert slow["taken"] == slow["express"] == 0
    assert fast["writes"] == slow["writes"]
    assert fast["events"] == slow["events"]
    assert fast["counts"] == slow["counts"]


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    job=_jobs(G2_ONLY),
    seed=st.integers(0, 2**32),
    error_rate=st.sampled_from([0.0, 0.0, 0.02, 0.2]),
    listening=st.booleans(),
)
def test_g2core_fast_path_writes_tells_and_counts_as_the_general_path(
    job: list[str], seed: int, error_rate: float, listening: bool
) -> None:
    _compare("g2core", job, seed, error_rate, listening)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    job=_jobs(GRBL_ONLY),
    seed=st.integers(0, 2**32),
    error_rate=st.sampled_from([0.0, 0.0, 0.02, 0.2]),
    listening=st.booleans(),
)
def test_grbl_fast_path_writes_tells_and_counts_as_the_general_path(
    job: list[str], seed: int, error_rate: float, listening: bool
) -> None:
    _compare("grbl", job, seed, error_rate, listening)


@pytest.mark.parametrize("dialect", ["g2core", "grbl"])
@pytest.mark.parametrize("special", ["$X", "G10 L20 P1 X0", "M0", "M6 T1", "G1 X1e5"])
def test_a_special_line_amid_plain_ones_is_written_as_the_general_path_writes_it(
    dialect: str, special: str
) -> None:
    """Where a run of plain lines stops short of the room (a `$` line, one that may
    store, a program pause, a hold point, a refused line), the express step leaves
    the rest of the step to the writer's loop: the same writes, in the same batches."""
    job = [PLAIN[i % len(PLAIN)] for i in range(24)] + [special]
    job += [PLAIN[i % len(PLAIN)] for i in range(24)]
    for seed in range(4):
        _compare(dialect, job, seed, 0.0, listening=False)


def test_a_plain_job_takes_the_fast_path_and_ends_complete() -> None:
    """The comparison above would pass with a fast path never taken: here it is taken,
    with the daemon's own look-ahead."""
    job = [PLAIN[i % len(PLAIN)] for i in range(600)]
    for dialect, listening in itertools.product(("g2core", "grbl"), (False, True)):
        run = asyncio.run(
            _run(dialect, True, job, 7, 0.0, listening, look_ahead=LOOK_AHEAD, queries=False)
        )
        sent, acked = run["counts"][:2]
        assert (sent, acked) == (600, 600)
        assert "completed" in run["counts"][8]
        # All but the job's last look-ahead and the window, answered once its input
        # ended; with a console listener that leaves the job's lines out (the
        # dashboard) as well.
        assert run["taken"] >= 600 - LOOK_AHEAD - 7
        # The express step (a read of plain answers, then the job's lines alone), also
        # while the dashboard listens to the console without the job's lines.
        assert run["express"] >= 50
        if listening:  # what it was told: the reports and the queries, no job line
            console = [e for e in run["events"] if e.startswith("Console(")]
            assert console and not any("job=True" in e for e in console)


def test_status_traffic_stays_out_of_a_console_that_does_not_want_it() -> None:
    """`status_traffic: false` (the dashboard unless its *polls* box is ticked): the
    host's status polls and the reports stay out of the console, and nothing else does."""
    job = [PLAIN[i % len(PLAIN)] for i in range(60)]
    for dialect in ("g2core", "grbl"):
        heard = asyncio.run(_run(dialect, True, job, 3, 0.0, listening=True))
        quiet = asyncio.run(_run(dialect, True, job, 3, 0.0, True, status_traffic=False))

        def console(run: Any) -> list[str]:
            return [e for e in run["events"] if e.startswith("Console(")]

        polls = [e for e in console(heard) if "status=True" in e]
        assert any("'tx'" in e for e in polls) and any("'rx'" in e for e in polls), polls
        assert [e for e in console(heard) if "status=False" in e] == console(quiet)
        assert not any("status=True" in e for e in console(quiet))
        assert any("status=False" in e for e in console(quiet))  # e.g. the handshake's
        assert (heard["writes"], heard["counts"]) == (quiet["writes"], quiet["counts"])


@pytest.mark.parametrize(
    ("dialect", "alarm"), [("g2core", b'{"sr":{"stat":2}}'), ("grbl", b"ALARM:1")]
)
def test_a_bug_in_the_express_step_halts_the_job_and_the_read_still_goes_in_full(
    dialect: str, alarm: bytes
) -> None:
    """`express` raising (a bug of ours) is met as one in `receive` is: the session halts,
    the job ends failed with an internal fault, no line of it is written after, and the
    read is still read in full, so that an alarm in it is not lost."""

    async def run() -> None:
        engine = Engine(_config(dialect), lambda event: None)
        board = Board(dialect, random.Random(1), 0.0)
        _connect(engine, board)
        stream = JobStream(iter(program_lines(PLAIN * 40)), 1, numbered=True)
        engine.start_stream(stream)
        for _ in range(10):
            engine.link_lines(Channel.DATA, board.read())
        assert stream.position.acked > 0 and not stream.done

        def broken(lines: list[bytes]) -> list[bytes] | None:
            raise RuntimeError("a bug of ours")

        engine.session.express = broken  # type: ignore[method-assign]
        written = len(board.writes)
        engine.link_lines(Channel.DATA, [*board.read(), alarm])
        assert engine.session.halted
        assert stream.done and "internal fault" in str(stream.position.result)
        assert engine.model.state is MachineState.ALARM
        assert not [data for kind, data in board.writes[written:] if kind == "lines"]

    asyncio.run(run())
