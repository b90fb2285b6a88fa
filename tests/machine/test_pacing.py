"""The engine's pacing: a link rests between reads only while a board answers at the pace
of its motion, never longer than PACE_MAX, and never when the board may be waiting.

A real `Engine` and each dialect's real session stream a job to the fast-path test's
board (tests/machine/test_fast_path.py), whose answers are handed to the engine one
read at a time on a clock the test moves; the link records each rest it is asked for.
The rest itself (nothing read meanwhile, everything read after, writes never held) is
tested on a real pty in tests/link/test_link.py.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import pytest

import hostd.machine.engine as engine_module
from hostd.link import Channel
from hostd.machine.engine import PACE_MAX, PACE_MIN, Engine, LinkState
from hostd.machine.stream import JobStream
from hostd.protocol.program import program_lines
from tests.machine.test_fast_path import G2_BANNER, Board, _config


class Draws:
    """The board's choices, fixed: reads of `take` lines, no reports, no errors."""

    def __init__(self) -> None:
        self.take = 1

    def randint(self, low: int, high: int) -> int:
        return max(low, min(self.take, high))

    def random(self) -> float:
        return 0.99


class RestingBoard(Board):
    def __init__(self, dialect: str) -> None:
        super().__init__(dialect, Draws(), 0.0)  # type: ignore[arg-type]
        self.rests: list[float] = []

    def rest(self, seconds: float) -> None:
        self.rests.append(seconds)

    def holds(self) -> int:
        return len(self.rx_used) if self.dialect == "grbl" else self.data_unanswered


class Run:
    """An engine streaming `lines` plain moves to a board, on the test's clock."""

    def __init__(self, dialect: str, monkeypatch: pytest.MonkeyPatch, lines: int = 400) -> None:
        self.now = 100.0
        monkeypatch.setattr(engine_module, "time", SimpleNamespace(monotonic=lambda: self.now))
        self.dialect = dialect
        self.engine = engine = Engine(_config(dialect))
        self.board = board = RestingBoard(dialect)
        engine.link = board  # type: ignore[assignment]
        engine.link_state = LinkState.HANDSHAKE
        engine.session.open()
        engine._deliver()
        if dialect == "g2core":
            board.owed.append(G2_BANNER)
        else:
            board.owed.extend([b"", b"Grbl 1.1h ['$' for help]"])
        self.read(take=100)
        while not engine.ready:
            self.read(take=100)
        self.stream = JobStream(
            iter(program_lines([f"G1 X{i % 7} F3000" for i in range(lines)])), 1, numbered=True
        )
        engine.start_stream(self.stream)
        # The board reports motion (g2core says so itself when its first line comes).
        if dialect == "grbl":
            self.engine.link_lines(Channel.DATA, [b"<Run|MPos:0.000,0.000,0.000|FS:0,0>"])

    def read(self, *, take: int, after: float = 0.001) -> list[bytes]:
        """`after` seconds on, one read of the board's next `take` lines."""
        self.now += after
        self.board.rng.take = take  # type: ignore[attr-defined]
        lines = self.board.read()
        if lines:
            self.engine.link_lines(Channel.DATA, lines)
        return lines

    def rests_during(self, **read: Any) -> list[float]:
        before = len(self.board.rests)
        self.read(**read)
        return self.board.rests[before:]


DIALECTS = ["g2core", "grbl"]


@pytest.mark.asyncio
@pytest.mark.parametrize("dialect", DIALECTS)
async def test_a_board_answering_at_its_motions_pace_is_read_a_few_answers_at_a_time(
    dialect: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    run = Run(dialect, monkeypatch)
    run.read(take=1)  # the first steady read: no pace known yet
    rests = []
    for _ in range(50):
        assert run.board.holds() >= 2  # the board holds unparsed lines: its planner is full
        rests += run.rests_during(take=1, after=0.001)
    assert len(rests) == 50
    # One answer a millisecond, the board holding 4 (g2core's window) or more: it would
    # answer half of them in 2 ms or more, so the rest is the cap, never over it.
    assert all(rest == pytest.approx(PACE_MAX) for rest in rests)
    # Answers 0.4 ms apart, one a read: the rest is 0.4 ms a half of what it holds, capped.
    rest = run.rests_during(take=1, after=0.0004)
    held = run.board.holds()
    assert rest == [pytest.approx(min(PACE_MAX, 0.0004 * (held // 2)))]


@pytest.mark.asyncio
@pytest.mark.parametrize("dialect", DIALECTS)
async def test_a_read_that_answers_everything_the_board_held_is_never_followed_by_a_rest(
    dialect: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The board may be waiting for lines (a fast board, or a host that was late)."""
    run = Run(dialect, monkeypatch)
    run.read(take=1)
    for _ in range(20):
        assert run.rests_during(take=100, after=0.01) == []
    assert run.stream.position.acked > 20


@pytest.mark.asyncio
@pytest.mark.parametrize("dialect", DIALECTS)
async def test_answers_that_come_fast_are_read_as_they_come(
    dialect: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A rest shorter than PACE_MIN is not worth its timer: an instant board never waits."""
    run = Run(dialect, monkeypatch)
    run.read(take=1)
    for _ in range(20):
        assert run.rests_during(take=1, after=PACE_MIN / 4) == []


@pytest.mark.asyncio
@pytest.mark.parametrize("dialect", DIALECTS)
async def test_no_rest_while_the_job_is_paused_or_after_its_input_ended(
    dialect: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    run = Run(dialect, monkeypatch, lines=60)
    run.read(take=1)
    assert run.rests_during(take=1) != []
    run.engine.pause_stream()  # its `!` written: what the board says now is read at once
    for _ in range(3):
        assert run.rests_during(take=1) == []
    run.engine.resume_stream()
    if dialect == "grbl":  # grbl says nothing of its own: its next report shows motion
        run.engine.link_lines(Channel.DATA, [b"<Run|MPos:0.000,0.000,0.000|FS:0,0>"])
    run.read(take=100)  # g2core: its report of the resumed motion among them
    assert run.rests_during(take=1) != []
    stream = run.engine.session.stream
    assert stream is not None
    while not stream.input_ended:
        run.read(take=1)
    # The file is all sent: each answer now checks whether the job is complete.
    while not run.stream.position.done:
        assert run.rests_during(take=1) == []


@pytest.mark.asyncio
async def test_a_rest_never_holds_a_realtime_byte_or_a_line(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The engine asks the link to rest its reading only: a pause's `!` still leaves in
    the call that asks for it."""
    run = Run("grbl", monkeypatch)
    run.read(take=1)
    assert run.rests_during(take=1) != []
    written = len(run.board.writes)
    run.engine.pause_stream()
    assert run.board.writes[written][0] == "realtime"
