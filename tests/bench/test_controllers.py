"""The bench's boards (bench/instant_controller.py) over a real pty, as a host sees them.

The figures are only as honest as the boards: a g2core that echoes N as at
jv 4, a grbl that answers `ok` per line, picks realtime bytes out of the
stream and counts a host that overfills its 128-byte receive buffer.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import select
import termios
import threading
import time
import tty
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from bench.client import DaemonProcess, program
from bench.instant_controller import Controller, GrblController, woken_at
from bench.procs import ControllerProcess


class Port:
    """The host's side: opened as a serial host opens it (raw, then a tcflush)."""

    def __init__(self, path: str) -> None:
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.fd)
        termios.tcflush(self.fd, termios.TCIOFLUSH)
        self.seen = b""

    def until(self, wanted: bytes, timeout: float = 10.0) -> bytes:
        """Read until `wanted` has come; what came up to its end."""
        deadline = time.monotonic() + timeout
        while wanted not in self.seen:
            left = deadline - time.monotonic()
            assert left > 0, f"no {wanted!r} in {self.seen!r}"
            if select.select([self.fd], [], [], left)[0]:
                self.seen += os.read(self.fd, 4096)
        end = self.seen.index(wanted) + len(wanted)
        got, self.seen = self.seen[:end], self.seen[end:]
        return got

    def write(self, data: bytes) -> None:
        os.write(self.fd, data)


# What each board prints when the host opens it, up to the end of its banner.
BANNERS = {"grbl": [b"Grbl 1.1h ['$' for help]\r\n"], "g2core": [b"SYSTEM READY", b"\n"]}


@contextlib.contextmanager
def opened(
    path: Path, dialect: str = "g2core", rate: float = 0.0
) -> Iterator[tuple[ControllerProcess, Port]]:
    """A bench board at `path` and the host's side of its port, its banner read."""
    board = ControllerProcess(str(path), dialect, rate=rate)
    port = Port(board.link)
    try:
        for part in BANNERS[dialect]:
            port.until(part)
        yield board, port
    finally:
        os.close(port.fd)
        board.close()


@pytest.fixture
def grbl(tmp_path: Path) -> Iterator[tuple[ControllerProcess, Port]]:
    with opened(tmp_path / "ttyGRBL", "grbl") as pair:
        yield pair


def test_grbl_says_its_buffer_and_planner_and_answers_each_line_ok(
    grbl: tuple[ControllerProcess, Port],
) -> None:
    board, port = grbl
    port.write(b"$I\n")
    assert port.until(b"ok\r\n") == b"[VER:1.1h.20190830:]\r\n[OPT:V,15,128]\r\nok\r\n"
    board.expect(2)
    port.write(b"N1 G1 X1 S10\nN2 G1 X2 S20\n")
    assert port.until(b"ok\r\nok\r\n").endswith(b"ok\r\nok\r\n")
    record = board.dump()
    assert record["job"]["lines"] == 2
    assert record["overflows"] == 0


def test_grbl_picks_realtime_bytes_out_of_a_line(grbl: tuple[ControllerProcess, Port]) -> None:
    board, port = grbl
    board.expect(3)
    port.write(b"G1 X1\nG1 X")  # a job under way, a line half-sent
    port.until(b"ok\r\n")
    port.write(b"!?~2\n")  # a hold, a report and a resume in the middle of the line
    assert port.until(b">\r\n").startswith(b"<Hold:0|MPos:")
    assert port.until(b"ok\r\n") == b"ok\r\n"  # the line itself, without the bytes picked out
    port.write(b"G1 X3\n")
    port.until(b"ok\r\n")
    port.write(b"?")
    assert port.until(b">\r\n").startswith(b"<Idle|")  # the job's last line: it stopped
    assert len(board.dump()["bangs"]) == 1


def test_grbl_counts_a_host_that_overfills_its_receive_buffer(
    grbl: tuple[ControllerProcess, Port],
) -> None:
    board, port = grbl
    port.write(b"$G\n")  # answered: frees its bytes
    port.until(b"ok\r\n")
    port.write(b"G1 X1.000 Y1.000 S100\n" * 6)  # 132 bytes unanswered at once: over 127
    for _ in range(6):
        port.until(b"ok\r\n")
    assert board.dump()["overflows"] > 0


def test_g2core_echoes_a_line_number_as_at_jv_4(tmp_path: Path) -> None:
    with opened(tmp_path / "ttyG2") as (_, port):
        port.write(b"N7 G1 X1\nG1 X2\nN0 G1 X3\n")
        answers = port.until(b'{"r":{},"f":[1,0,9]}\n')  # the third line's: N0 is not echoed
        assert answers.endswith(
            b'{"r":{"n":7},"f":[1,0,9]}\n{"r":{},"f":[1,0,6]}\n{"r":{},"f":[1,0,9]}\n'
        )


def test_g2core_answers_a_text_mode_get_in_json_as_the_daemons_kill_fence_needs(
    tmp_path: Path,
) -> None:
    """`$stat` behind a ^D (docs/protocol.md, "A kill's fence"): g2core answers a text-mode
    GET in JSON mode with the key's value (text_parser.cpp:84-96). Answered as a G-code
    line instead, the daemon took it for an answer it could not place: the bench's P2
    stopped on a `lexical` fault after P1's cancel."""
    with opened(tmp_path / "ttyG2") as (_, port):
        port.write(b"$stat\n")
        assert port.until(b"\n") == b'{"r":{"stat":3},"f":[1,0,6]}\n'


def test_a_rastering_grbl_answers_as_its_planner_takes_the_lines(tmp_path: Path) -> None:
    """15 blocks at 50 a second: 20 lines sent at once are answered over about 0.1 s,
    and nothing is recorded as starving while the host keeps it fed."""
    with opened(tmp_path / "ttyR", "grbl", rate=50.0) as (board, port):
        board.expect(20)
        port.write(b"G1 X1\n" * 20)  # 120 bytes: fits the buffer
        first = port.until(b"ok\r\n" * 15)  # the planner's 15 blocks, at once
        assert first.count(b"ok") == 15
        port.write(b"?")
        report = port.until(b">\r\n")
        assert report.startswith(b"<Run|") and b"|Bf:0," in report
        port.until(b"ok\r\n" * 5)  # the other five, as blocks run
        record = board.dump()
        assert record["job"]["lines"] == 20
        assert record["starved"] == []


def test_a_rastering_g2core_never_leaves_a_host_with_a_full_window_waiting(
    tmp_path: Path,
) -> None:
    """A host keeping 4 lines unanswered gets every answer as the planner takes its line,
    with no input of its own to wake the board. (The board slept until its next input when a
    block freed between its planning and its choice of how long to sleep: the host, its
    window full of the lines waiting, sent none, and P8 counted a second's stall as the
    host's starvation.) 3,000 lines at 2,000 a second met that race about every 1,000."""
    with opened(tmp_path / "ttyR", "g2core", rate=2000.0) as (board, port):
        total = 3000
        board.expect(total)
        sent = answered = 0
        while answered < total:
            while sent < total and sent - answered < 4:
                sent += 1
                port.write(b"N%d G1 X%d\n" % (sent, sent % 10))
            answered += 1
            port.until(b'{"r":{"n":%d}' % answered, timeout=2.0)
        assert board.dump()["job"]["lines"] == total


class Stepped:
    """A bench board in this process, its loop turned by the test: its commands through
    a pipe of the test's, its answers kept, and each turn (`Controller.step`) taken when
    the test has arranged what the turn finds."""

    def __init__(
        self, path: Path, rate: float, blocks: int, board: type[Controller] = Controller
    ) -> None:
        self.board = board(str(path), rate, blocks)
        self.commands, self._commands_w = os.pipe()
        self.board.commands = self.commands
        self.answers = io.StringIO()
        self.board.answers = self.answers
        self.port = Port(self.board.link)

    def command(self, text: str) -> None:
        os.write(self._commands_w, text.encode() + b"\n")

    def turn_until(self, wanted: bytes) -> bytes:
        """Turn the loop (never sleeping long) until the host has read `wanted`."""
        deadline = time.monotonic() + 10.0
        while wanted not in self.port.seen:
            assert time.monotonic() < deadline, f"no {wanted!r} in {self.port.seen!r}"
            self.board.step(limit=0.01)
            if select.select([self.port.fd], [], [], 0)[0]:
                self.port.seen += os.read(self.port.fd, 4096)
        return self.port.until(wanted)

    def turn_alone(self) -> bool:
        """One turn as the board's process takes it, with nothing from the test to end its
        sleep: False if it was still asleep (blocked) after a long while; then a byte
        from the host (an empty line, which the board ignores) wakes it."""
        turn = threading.Thread(target=self.board.step)
        turn.start()
        turn.join(timeout=5.0)
        if not turn.is_alive():
            return True
        self.port.write(b"\n")
        turn.join()
        return False

    def dumped(self) -> dict[str, Any]:
        """The board's last answer to `dump` (its answers also say `opened`)."""
        record: dict[str, Any] = json.loads(self.answers.getvalue().splitlines()[-1])
        return record

    def close(self) -> None:
        os.close(self.port.fd)
        os.close(self.commands)
        os.close(self._commands_w)
        self.board.close()


@pytest.fixture
def stepped(tmp_path: Path) -> Iterator[Stepped]:
    """A rastering g2core of one block at 5 a second (a line waits up to 0.2 s for it),
    opened by the host and its banner read."""
    pair = Stepped(tmp_path / "ttyS", rate=5.0, blocks=1)
    try:
        pair.turn_until(b"SYSTEM READY")
        pair.turn_until(b"\n")
        yield pair
    finally:
        pair.close()


def test_a_dump_that_reads_the_hosts_line_leaves_the_board_awake_for_its_block(
    stepped: Stepped,
) -> None:
    """The bench's `dump` reads the port itself (a `!` written just before it is counted).
    When the same wake-up also had the port readable, the loop then read the port again,
    found nothing, and (blocking) slept in that read until the host wrote. A host whose
    window was full of lines waiting for a block never did: P8 saw a g2core board stream
    2 lines a second, `late` 2.0 s, until the daemon's heartbeat (2 s of silence) wrote a
    status query (a grbl board: until the next `?`, 0.25 s). Here the host's line and the
    dump arrive together, as they did then, while the planner's one block is busy."""
    stepped.port.write(b"N1 G1 X1\n")
    stepped.turn_until(b'{"r":{"n":1}')  # planned: the planner's one block
    stepped.port.write(b"N2 G1 X2\n")  # waits for that block
    assert select.select([stepped.board.fd], [], [], 10.0)[0]  # the board can read it
    stepped.command("dump")
    assert stepped.turn_alone(), "the board slept in a read of its port after a dump"
    assert stepped.dumped()["job"]["lines"] >= 1  # answered (N2 too, if its block freed)
    # Nothing more from the host: the block's end alone gets N2 its answer.
    assert stepped.turn_until(b'{"r":{"n":2}').endswith(b'{"r":{"n":2}')
    assert stepped.board.rescued == 0  # its deadline woke it, not the safety net


def test_a_board_that_misses_its_deadline_is_woken_by_its_safety_net_and_says_so(
    stepped: Stepped, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The earlier stall (4b1eba1): no deadline while lines waited. Made again here (the
    planner's deadline left out), the safety net still plans the line once its block is
    free, and the dump counts the rescue, so that P8 says a board had a bug."""
    monkeypatch.setattr(stepped.board, "_deadlines", list)
    stepped.port.write(b"N1 G1 X1\nN2 G1 X2\n")
    assert select.select([stepped.board.fd], [], [], 10.0)[0]
    assert stepped.turn_alone()  # reads both: N1 takes the one block, N2 waits for it
    assert stepped.board.waiting
    while b'{"r":{"n":2}' not in stepped.port.seen:
        assert stepped.turn_alone(), "the board slept with a line waiting"
        if select.select([stepped.port.fd], [], [], 0)[0]:
            stepped.port.seen += os.read(stepped.port.fd, 4096)
    stepped.command("dump")
    assert stepped.turn_alone()
    assert stepped.dumped()["rescued"] == 1


# -- a read's first line, given the time its input woke the board's process -------------


def test_a_wake_is_the_ports_only_when_it_slept_once_and_only_the_port_woke_it() -> None:
    """`woken_at`: the run-queue wait comes off `now` when the process slept once (one time
    slice more), the port alone was ready and the wake came before the deadline; any
    other case is None, and the line keeps the time it was read (against the host)."""
    before, waited = (5, 1_000, 7), (9, 31_000_000 + 1_000, 8)  # 31 ms on a run queue
    assert woken_at(True, None, before, waited, 100.0) == pytest.approx(100.0 - 0.031)
    assert woken_at(True, 101.0, before, waited, 100.0) == pytest.approx(99.969)
    assert woken_at(False, None, before, waited, 100.0) is None  # a command came too
    assert woken_at(True, 99.95, before, waited, 100.0) is None  # the timeout's, maybe
    twice = (9, 31_001_000, 9)  # put off the CPU before it slept, or after it woke
    assert woken_at(True, None, before, twice, 100.0) is None
    assert woken_at(True, None, before, (9, 1_000, 7), 100.0) is None  # it never slept
    assert woken_at(True, None, before, (9, 1_000, 8), 100.0) is None  # it ran at once


class FakeRunQueue:
    """Each `poll` seen as a sleep of `slices` time slices after which the process waited
    `wait` seconds on a run queue (the readings alternate: before, after)."""

    def __init__(self, wait: float, slices: int = 1) -> None:
        self.wait, self.slices, self.calls = int(wait * 1e9), slices, 0

    def read(self) -> tuple[int, int, int]:
        self.calls += 1
        turn, after = divmod(self.calls - 1, 2)
        return (0, turn * self.wait + after * self.wait, turn * self.slices + after * self.slices)

    def close(self) -> None:
        pass


def _first_arrival(pair: Stepped, data: bytes, queue: FakeRunQueue, answer: bytes) -> float:
    """How much earlier than the read the board says the job's first line arrived."""
    pair.board._run_queue = queue  # type: ignore[assignment]
    pair.command("expect 1")
    assert select.select([pair.commands], [], [], 10.0)[0]
    pair.board.step(limit=0.01)  # the command read alone: no port input in that turn
    pair.port.write(data)
    assert select.select([pair.board.fd], [], [], 10.0)[0]
    pair.turn_until(answer)
    read_by = time.monotonic()
    pair.command("dump")
    assert pair.turn_alone()
    first: float = pair.dumped()["job"]["first"]
    return read_by - first


def test_a_reads_first_line_arrived_when_the_port_woke_the_board(stepped: Stepped) -> None:
    """A board process kept off the CPU for 10 s after the host's line woke it: the line
    arrived at the wake, not 10 s later, and the dump says one line was credited."""
    early = _first_arrival(stepped, b"N1 G1 X1\n", FakeRunQueue(10.0), b'{"r":{"n":1}')
    assert early >= 10.0
    assert stepped.dumped()["credited"] == 1
    assert stepped.dumped()["credited_most"] >= 10.0


@pytest.mark.parametrize(
    ("data", "slices"),
    [
        (b"N1 G1 X1\n", 2),  # put off the CPU before it slept or after it woke
        (b'{"sr":null}\nN1 G1 X1\n', 1),  # another line came first: it woke the board
    ],
    ids=["two slices", "a control line first"],
)
def test_no_line_is_credited_when_the_wake_may_not_be_its_own(
    stepped: Stepped, data: bytes, slices: int
) -> None:
    early = _first_arrival(stepped, data, FakeRunQueue(10.0, slices), b'{"r":{"n":1}')
    assert early < 10.0
    assert stepped.dumped()["credited"] == 0


def test_a_grbl_read_led_by_a_realtime_byte_credits_no_line(tmp_path: Path) -> None:
    """grbl picks realtime bytes out of a read: a `?` may have been what woke the board,
    with the line after it written later; the line keeps the time it was read. The same
    line alone is credited."""
    pair = Stepped(tmp_path / "ttyG", rate=5.0, blocks=1, board=GrblController)
    try:
        pair.turn_until(b"Grbl 1.1h ['$' for help]\r\n")
        assert _first_arrival(pair, b"?G1 X1\n", FakeRunQueue(10.0), b"ok") < 10.0
        assert pair.dumped()["credited"] == 0
        assert _first_arrival(pair, b"G1 X2\n", FakeRunQueue(10.0), b"ok") >= 10.0
        assert pair.dumped()["credited"] == 1
    finally:
        pair.close()


@pytest.mark.parametrize("dialect", ["grbl", "g2core"])
def test_a_real_daemon_connects_to_the_bench_board_and_runs_a_job(
    tmp_path: Path, dialect: str
) -> None:
    """The daemon's handshake goes through with each bench board, as `make bench` needs:
    a grbl board that answered `$N` with a bare `ok` was never connected to once the
    handshake asked for `$N`'s printout (performance-log.md, 2026-11-29 10:35)."""
    board = ControllerProcess(str(tmp_path / "ttyB"), dialect)
    daemon = DaemonProcess(tmp_path, board.link, window=4, dialects={"bench": dialect})
    try:
        daemon.start()  # idle, or TimeoutError: the handshake never finished
        client = daemon.client()
        try:
            client.upload("p.gcode", program(200))
            client.call("subscribe", topics=["job"], machine="bench")
            board.expect(200)
            job_id = client.call("job.start", machine="bench", file="p.gcode")["job"]
            job = client.wait_job_end(job_id, timeout=60)
            assert job["state"] == "completed" and job["lines_acked"] == 200, job
        finally:
            client.close()
    finally:
        daemon.stop()
        board.close()
