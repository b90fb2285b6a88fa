"""The bench's planner model (bench/planner.py): P8's starvation count is only as good as it.

Pure arithmetic on given times, no clock read: a host that keeps ahead never
starves the board, a late line starves it for exactly its lateness, and
neither the controller process waking late nor a feedhold counts against
the host.
"""

from __future__ import annotations

from bench.planner import Planner


def job(planner: Planner, arrivals: list[tuple[float, float]]) -> None:
    """Plan a job's lines: (read at, handled at) each, the first one opening the job."""
    for i, (arrival, now) in enumerate(arrivals):
        planner.add(arrival, now)
        if i == 0:
            planner.begin_job()


def test_a_host_that_keeps_ahead_never_starves_the_board() -> None:
    planner = Planner(blocks=3, period=1.0)
    job(planner, [(0.0, 0.0), (0.1, 0.1), (0.2, 0.2), (1.0, 1.0), (2.0, 2.0), (3.0, 3.0)])
    assert planner.starved == []
    assert planner.last_done == 6.0  # six blocks back to back from 0


def test_a_late_line_starves_the_board_for_exactly_its_lateness() -> None:
    planner = Planner(blocks=3, period=1.0)
    job(planner, [(0.0, 0.0), (0.5, 0.5), (3.5, 3.5)])  # the second block ends at 2.0
    assert [(s.at, s.seconds) for s in planner.starved] == [(2.0, 1.5)]


def test_a_line_that_waited_for_a_block_is_planned_when_the_block_freed() -> None:
    """The controller handling it late (now=5) is its own delay, not the host's."""
    planner = Planner(blocks=1, period=1.0)
    job(planner, [(0.0, 0.0), (0.1, 5.0), (0.2, 5.0)])
    assert planner.starved == []
    assert planner.last_done == 3.0


def test_the_planner_is_full_until_a_block_has_run() -> None:
    planner = Planner(blocks=2, period=1.0)
    job(planner, [(0.0, 0.0), (0.0, 0.0)])
    assert planner.queued(0.5) == 2
    assert planner.next_free_wall(0.5) == 1.0
    assert planner.queued(1.0) == 1


def test_time_held_is_no_starvation_and_runs_no_block() -> None:
    planner = Planner(blocks=2, period=1.0)
    job(planner, [(0.0, 0.0)])
    planner.hold(0.5)
    assert planner.queued(5.0) == 1  # held: the block does not finish
    planner.resume(10.5)
    planner.add(10.6, 10.6)  # 0.6 s of running time after the start: the block still runs
    assert planner.starved == []
    assert planner.to_wall(planner.last_done) == 12.0


def test_after_the_last_line_the_planner_drains_without_starving() -> None:
    planner = Planner(blocks=2, period=1.0)
    job(planner, [(0.0, 0.0), (0.5, 0.5)])
    planner.end_job()
    planner.add(10.0, 10.0)  # the next job's first line, long after
    assert planner.starved == []
