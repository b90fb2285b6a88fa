"""The bench's boards (bench/instant_controller.py) over a real pty, as a host sees them.

The figures are only as honest as the boards: a g2core that echoes N as at
jv 4, a grbl that answers `ok` per line, picks realtime bytes out of the
stream and counts a host that overfills its 128-byte receive buffer.
"""

from __future__ import annotations

import contextlib
import os
import select
import termios
import time
import tty
from collections.abc import Iterator
from pathlib import Path

import pytest

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
