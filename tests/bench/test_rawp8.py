"""P8's bare host (bench/rawp8.py) against the bench's boards over real ptys.

It is P8's baseline: the least a host of the daemon's shape pays to keep the
boards fed. A baseline that overfilled a grbl's receive buffer or kept more
than its window unanswered would be cheaper than any host may be, and the
daemon would be held to a floor no correct host stands on. So: every line
answered, the flow control kept, and it stops when told or when a port goes.
No cgroup here (that needs root): the bench puts it in one.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import select
import subprocess
import sys
from collections.abc import Coroutine, Iterator
from pathlib import Path
from typing import Any, TypeVar

import pytest
import uvloop

from bench.client import raster
from bench.procs import ControllerProcess
from bench.raw import wire_lines
from bench.rawp8 import HostWindow, open_ports, run, stream
from bench.run import _bare_baseline

T = TypeVar("T")
LINES = 300


def on_uvloop(coroutine: Coroutine[Any, Any, T], timeout: float = 30.0) -> T:
    """Run it on uvloop, as the bare host runs; a hang fails the test instead."""
    return uvloop.run(asyncio.wait_for(coroutine, timeout))


@contextlib.contextmanager
def boards(
    tmp_path: Path, dialect: str, count: int, *, rate: float = 0.0, blocks: int | None = None
) -> Iterator[list[ControllerProcess]]:
    made: list[ControllerProcess] = []
    try:
        for i in range(count):
            made.append(
                ControllerProcess(str(tmp_path / f"tty{i}"), dialect, rate=rate, blocks=blocks)
            )
        yield made
    finally:
        for board in made:
            board.close()


def test_grbl_lines_all_answered_and_the_receive_buffer_never_overfilled(
    tmp_path: Path,
) -> None:
    """Two grbl boards whose planner of 2 blocks takes a line every 0.1 ms: lines wait in
    the 128-byte receive buffer, which character counting must fill and never overfill."""
    with boards(tmp_path, "grbl", 2, rate=10_000.0, blocks=2) as grbls:
        for board in grbls:
            board.expect(LINES)
        lines = wire_lines(raster(LINES))
        ports = on_uvloop(stream([b.link for b in grbls], "grbl", lines))
        records = [board.dump() for board in grbls]
    assert [p.acked for p in ports] == [LINES, LINES]
    assert [r["job"]["lines"] for r in records] == [LINES, LINES]
    assert [r["overflows"] for r in records] == [0, 0]
    assert all(p.used == 0 for p in ports)  # every byte written was answered


def test_g2core_never_more_than_its_window_unanswered(tmp_path: Path) -> None:
    """Two g2core boards whose planner of one block takes a line every 0.5 ms: lines wait,
    and the board counts what it holds unanswered at each read."""
    with boards(tmp_path, "g2core", 2, rate=2_000.0, blocks=1) as g2s:
        for board in g2s:
            board.expect(LINES)
        lines = wire_lines(raster(LINES))
        ports = on_uvloop(stream([b.link for b in g2s], "g2core", lines, window=4))
        records = [board.dump() for board in g2s]
    assert [p.acked for p in ports] == [LINES, LINES]
    assert [r["job"]["lines"] for r in records] == [LINES, LINES]
    assert [r["unanswered"] for r in records] == [4, 4]  # the window kept full, no more


def test_a_g2core_board_counts_a_host_that_overruns_its_window(tmp_path: Path) -> None:
    """What the test above reads: a window of 6 shows as 6 (the board sees the overrun)."""
    with boards(tmp_path, "g2core", 1, rate=2_000.0, blocks=1) as g2s:
        g2s[0].expect(50)
        on_uvloop(stream([g2s[0].link], "g2core", wire_lines(raster(50)), window=6))
        assert g2s[0].dump()["unanswered"] == 6


def test_a_port_that_goes_mid_stream_ends_it_with_an_error(tmp_path: Path) -> None:
    """A board that vanishes (its process gone, the pty's other side closed) is a
    ConnectionError, not a bare host waiting for answers for ever."""
    with boards(tmp_path, "g2core", 1, rate=200.0, blocks=1) as g2s:
        board = g2s[0]

        async def vanish() -> None:
            ports = await open_ports([board.link], "g2core", wire_lines(raster(10_000)), 4)
            go = asyncio.ensure_future(run(ports))
            await asyncio.sleep(0)  # started: its first lines written
            assert ports[0].sent == 4
            board.close()
            await go

        with pytest.raises(ConnectionError):
            on_uvloop(vanish())


def _said(host: subprocess.Popen[str], timeout: float = 30.0) -> str:
    assert host.stdout is not None
    assert select.select([host.stdout], [], [], timeout)[0], "bench.rawp8 said nothing"
    return host.stdout.readline().strip()


@contextlib.contextmanager
def helper(dialect: str, lines: int, links: list[str]) -> Iterator[subprocess.Popen[str]]:
    """`python -m bench.rawp8` as the bench starts it (without the cgroup)."""
    host = subprocess.Popen(
        [sys.executable, "-m", "bench.rawp8", "--dialect", dialect, "--lines", str(lines), *links],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert _said(host) == "ready"
        yield host
    finally:
        if host.poll() is None:
            host.kill()
        host.wait()


def _tell(host: subprocess.Popen[str], word: str) -> None:
    assert host.stdin is not None
    host.stdin.write(word + "\n")
    host.stdin.flush()


def test_the_helper_streams_on_go_and_says_its_counts_when_done(tmp_path: Path) -> None:
    with boards(tmp_path, "grbl", 2) as grbls:
        for board in grbls:
            board.expect(LINES)
        with helper("grbl", LINES, [b.link for b in grbls]) as host:
            assert [b.dump()["job"]["lines"] for b in grbls] == [0, 0]  # nothing before `go`
            _tell(host, "go")
            result = json.loads(_said(host))
            assert host.wait(10) == 0
        records = [board.dump() for board in grbls]
    assert result == {"acked": [LINES, LINES], "sent": [LINES, LINES]}
    assert [r["job"]["lines"] for r in records] == [LINES, LINES]
    assert [r["overflows"] for r in records] == [0, 0]


def test_the_helper_stops_mid_stream_when_told(tmp_path: Path) -> None:
    """The bench stops it after its window; a job of 10,000 lines at 200 a second is far
    from its end then. The streams it ends say nothing (once, a complaint on stderr
    about a cancelled wait nobody read)."""
    with boards(tmp_path, "g2core", 1, rate=200.0, blocks=1) as g2s:
        g2s[0].expect(10_000)
        with helper("g2core", 10_000, [g2s[0].link]) as host:
            _tell(host, "go")
            _tell(host, "stop")
            result = json.loads(_said(host))
            assert host.wait(10) == 0
            assert host.stderr is not None
            assert host.stderr.read() == ""
    assert len(result["acked"]) == 1
    assert result["acked"][0] < 10_000
    assert result["sent"][0] - result["acked"][0] <= 4


def _window(starved: list[list[float]]) -> HostWindow:
    record = {"job": {"lines": 4000}, "starved": starved, "overflows": 0, "late": 0.001}
    return HostWindow([record, dict(record, starved=[])], 2.0, 0.3, 200, 0, 0.0)


def test_p8s_row_puts_the_bare_host_beside_the_daemon() -> None:
    baseline, notes = _bare_baseline(_window([]), daemon_us=62.0)
    assert baseline == "bare host: 2,000 lines/s each, 38 us/line, starved 0x"
    assert "38 us a line against the daemon's 62" in notes[0]
    assert len(notes) == 1  # nothing to excuse


def test_a_bare_host_that_starved_the_boards_is_called_the_machines_floor() -> None:
    """A target a bare host misses in the same cgroup is not the daemon's to meet:
    the row says so rather than letting the daemon's FAIL read as the daemon's."""
    _, notes = _bare_baseline(_window([[1.0, 0.004], [1.5, 0.002]]), daemon_us=62.0)
    assert any(
        "bare host itself starved the boards 2x, 6.0 ms in all, longest 4.0 ms" in note
        and "not the daemon's to meet" in note
        for note in notes
    )
