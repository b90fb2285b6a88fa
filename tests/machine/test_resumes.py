"""The Machine side of a resume (hostd/machine/resumes.py): which job resumes at which
line, and what of the machine goes into its plan (its laser mode, dwell, plunge feed,
safe height, the board's offsets), the gaps a mutation campaign found.

The machines here are never connected: the board's offsets are given (as
`board_offsets` would read them), or not readable. The plan is made in this process:
`plan_at` hands the pool nothing but the planning function and its arguments.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar, cast

import pytest

from hostd.machine.jobstore import Job, JobStore
from hostd.machine.machine import Machine
from hostd.machine.resumes import NotResumable, _recovery_line, plan_at, plan_with
from hostd.machine.workers import WorkerPool
from hostd.protocol.dialects import lookup
from hostd.protocol.gcodestate.resume import Board
from hostd.protocol.limits import MachineLimits
from tests.machine.conftest import machine_config
from tests.protocol.test_resume_plan import BOARD, OFFSETS

T = TypeVar("T")
MILL = "G21 G90\nG0 X0 Y0 Z5\nS9000 M3\nG1 Z-2 F300\nG1 X20 F900\nG1 Y5\n"
LASER = "G21 G90\nG0 X5 Y5 Z0\nM4 S800\nG1 X20 F3000\nG1 Y20\n"


class _Here:
    """A worker pool that runs the planning in this process."""

    async def run(self, what: str, fn: Callable[..., T], *args: Any) -> T:
        return fn(*args)


POOL = cast(WorkerPool, _Here())


def _job(**fields: object) -> Job:
    row: dict[str, object] = {
        "id": 7,
        "machine": "m1",
        "file": "part.nc",
        "kind": "make",
        "state": "interrupted",
        "lines_total": 20,
        "lines_sent": 20,
        "lines_acked": 12,
        "started_at": None,
        "ended_at": None,
        "error": None,
    }
    return Job.model_validate(row | fields)


@pytest.fixture
def machines(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Callable[..., Machine]]:
    """A machine of the config given whose board holds `board` (None: not readable)."""
    stores: list[JobStore] = []

    def make(board: Board | None, **config: object) -> Machine:
        jobs = tmp_path / "jobs"
        jobs.mkdir(exist_ok=True)
        stores.append(JobStore(tmp_path / f"jobs{len(stores)}.db"))
        machine = Machine(machine_config(str(tmp_path / "tty"), **config), stores[-1], jobs)
        if board is not None:

            async def read() -> Board:
                return board

            monkeypatch.setattr(machine, "board_offsets", read)
        return machine

    yield make
    for store in stores:
        store.close()


def _file(tmp_path: Path, text: str, name: str = "part.nc") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


# -- which job, which line ------------------------------------------------------------


@pytest.mark.parametrize("state", ["interrupted", "failed", "cancelled"])
def test_a_lost_make_job_resumes_at_the_line_the_board_last_ran(state: str) -> None:
    line, about = _recovery_line(_job(state=state, line_executed=9))
    assert line == 9 and "it answered 12 of the job's lines" in about[0]


@pytest.mark.parametrize("state", ["completed", "running", "paused"])
def test_a_job_that_completed_or_still_runs_has_no_resume(state: str) -> None:
    """api.md 1011: a job that completed (or has not ended) is not resumed."""
    with pytest.raises(NotResumable, match=f"job 7 is {state}: only interrupted, failed"):
        _recovery_line(_job(state=state, line_executed=9))


def test_a_job_whose_board_never_said_its_line_resumes_at_the_jobs_own_first_line() -> None:
    """A job that itself started at line 60 resumes there, not at line 1 (which would
    run again every line before 60, which that job skipped)."""
    assert _recovery_line(_job(start_line=60)) == (
        60,
        ["the board never said which line it ran: resuming at the job's start"],
    )
    assert _recovery_line(_job())[0] == 1


# -- the file ------------------------------------------------------------------------


@pytest.mark.asyncio
async def test_a_resume_at_a_comment_is_planned_at_the_next_line_the_board_runs(
    tmp_path: Path,
) -> None:
    path = _file(tmp_path, "G21 G90\nG0 X0 Y0 Z5\nS9000 M3\nG1 Z-1 F200\n(pass 2)\n\nG1 X20 F900\n")
    plan = await plan_at(path, 5, lookup("grbl"), board=BOARD, safe_z=-2.0, dwell=1.0, pool=POOL)
    assert plan.line == 7
    assert plan.approach[1:] == [
        "G53 G0 X100 Y100",
        "S9000 M3",
        "G4 P1",
        "G53 G1 Z-81 F200",
        "F200",
    ]


@pytest.mark.asyncio
async def test_a_resume_with_nothing_to_run_after_it_or_no_file_is_refused(
    tmp_path: Path,
) -> None:
    path = _file(tmp_path, "G21 G90\nG0 X0 Y0 Z5\nG1 Z-1 F200\nG1 X20 F900\n(end)\n\n")
    args: dict[str, Any] = {"board": BOARD, "safe_z": -2.0, "dwell": 1.0, "pool": POOL}
    with pytest.raises(NotResumable, match="nothing to run at or after line 5"):
        await plan_at(path, 5, lookup("grbl"), **args)
    with pytest.raises(NotResumable, match=r"no file 'gone\.nc' in the jobs directory"):
        await plan_at(tmp_path / "gone.nc", 2, lookup("grbl"), **args)


# -- the machine ---------------------------------------------------------------------


@pytest.mark.asyncio
async def test_a_grbl_board_in_laser_mode_resumes_as_a_laser(
    machines: Callable[..., Machine], tmp_path: Path
) -> None:
    """operations.md, `laser`: a grbl board in laser mode ($32=1) counts as a laser,
    whatever the config says: the beam goes on only in position, and without a dwell."""
    machine = machines(Board(OFFSETS, speed=1000.0), dialect="grbl", safe_z=-2.0)
    machine.engine.model.laser_mode = True  # as the board's $32 said
    plan = await plan_with(machine, _file(tmp_path, LASER), 5, None, POOL)
    assert plan.approach == [
        "G90 G53 G0 Z-2",
        "G53 G0 X120 Y105",
        "G53 G1 Z-80 F3000",
        "S800 M4",
        "F3000",
    ]


@pytest.mark.asyncio
async def test_the_machines_dwell_and_plunge_feed_go_into_the_approach(
    machines: Callable[..., Machine], tmp_path: Path
) -> None:
    machine = machines(BOARD, safe_z=-2.0, spindle_dwell=3.5, plunge_feed=120.0)
    plan = await plan_with(machine, _file(tmp_path, MILL), 6, None, POOL)
    assert plan.approach == [
        "G90 G53 G0 Z-2",
        "G53 G0 X120 Y100",
        "S9000 M3",
        "G4 P3.5",
        "G53 G1 Z-82 F120",
        "F900",
    ]


@pytest.mark.asyncio
async def test_without_safe_z_a_homed_machine_climbs_to_the_top_of_its_travel(
    machines: Callable[..., Machine], tmp_path: Path
) -> None:
    """operations.md, `safe_z`: none set, the top of the Z travel once homed; unhomed,
    no safe height, and no plan."""
    path = _file(tmp_path, MILL)
    limits = MachineLimits(travel={"z": (-100.0, -1.5)})
    machine = machines(BOARD)
    machine.engine.model.homed = True
    assert (await plan_with(machine, path, 6, limits, POOL)).approach[0] == "G90 G53 G0 Z-1.5"
    machine.engine.model.homed = False
    with pytest.raises(NotResumable, match="no safe height"):
        await plan_with(machine, path, 6, limits, POOL)


@pytest.mark.asyncio
async def test_a_board_whose_offsets_cannot_be_read_gets_no_plan(
    machines: Callable[..., Machine], tmp_path: Path
) -> None:
    with pytest.raises(NotResumable, match="m1: its board's offsets could not be read"):
        await plan_with(machines(None, safe_z=-2.0), _file(tmp_path, MILL), 6, None, POOL)
