"""Before a job moves anything: its analysis against the machine, and a resume's plan.

The G-code rules are in `hostd.protocol.gcodestate` (the model, the analysis, the
resume plan) and the dialect's settings in its session (`limit_settings`,
`machine_limits`); this module reads the file off the event loop and puts them
together for one machine. The functions that take a `Machine` (`analyze_for`,
`prepare_start`, `plan_for`, `recovery_for`) read what they need of it
themselves: its board's limits (none when the board cannot say), its work
offset, safe height and dwell.
"""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import structlog

from hostd.machine.jobstore import Job
from hostd.machine.machine import Machine
from hostd.protocol.errors import MachineError
from hostd.protocol.gcodestate import DIALECTS, Analysis, analyze
from hostd.protocol.gcodestate.analysis import beyond_travel
from hostd.protocol.gcodestate.resume import Board, ResumeError, ResumePlan, plan_resume
from hostd.protocol.gcodestate.state import MM_PER_INCH
from hostd.protocol.limits import MachineLimits
from hostd.protocol.program import program_lines

log = structlog.get_logger(__name__)

RESUMABLE = ("interrupted", "failed", "cancelled")


class OutOfTravel(MachineError):
    """The program's moves leave the machine's travel (`force` to run it anyway)."""

    code = 1010


class NotResumable(MachineError):
    """No safe resume: the job, the file or the position does not allow one."""

    code = 1011


@dataclass(frozen=True, slots=True)
class Preflight:
    analysis: Analysis
    limits: MachineLimits | None
    beyond: list[str]  # why the program leaves the travel, axis by axis
    checked: bool = False  # the travel and the work offset were known: the check ran

    def to_json(self) -> dict[str, Any]:
        a = self.analysis
        return {
            "lines": a.lines,
            "blocks": a.blocks,
            "moves": a.rapids + a.feeds,
            "rapids": a.rapids,
            "feeds": a.feeds,
            "arcs": a.arcs,
            "bounds": {axis: list(b) for axis, b in a.bounds.items()},
            "units": list(a.units),
            "tools": list(a.tools),
            "max_speed": a.max_speed,
            "estimate": round(a.seconds, 3),
            "warnings": [{"text": w.text, "line": w.line, "count": w.count} for w in a.warnings]
            + [{"text": text, "line": None, "count": 1} for text in self.beyond],
            "beyond_travel": self.beyond,
            "travel_checked": self.checked,
            "limits": None if self.limits is None else self.limits.to_json(),
        }


def work_offset(snapshot: dict[str, Any]) -> dict[str, float] | None:
    """Machine minus work position (mm) as the board reports them: the offset in force.

    None until the machine is homed: machine coordinates mean nothing before (a board
    counts from wherever it was switched on), so neither does a travel check.
    """
    if snapshot.get("homed") is not True:
        return None
    machine = snapshot.get("machine_position") or {}
    work = snapshot.get("work_position") or {}
    scale = MM_PER_INCH if snapshot.get("units") == "in" else 1.0
    return {a: (machine[a] - work[a]) * scale for a in machine if a in work}


async def analyze_file(
    path: Path,
    dialect: str,
    limits: MachineLimits | None = None,
    offset: dict[str, float] | None = None,
) -> Preflight:
    """The file's figures, its estimate with the machine's speeds, and its travel check."""

    def run() -> Analysis:
        with path.open("rb") as f:
            fingerprint = hashlib.file_digest(f, "blake2b").digest()
        velocity = tuple(sorted(limits.velocity.items())) if limits else ()
        acceleration = tuple(sorted(limits.acceleration.items())) if limits else ()
        return _analysis(path, fingerprint, dialect, velocity, acceleration)

    analysis = await asyncio.to_thread(run)
    beyond: list[str] = []
    checked = limits is not None and bool(limits.travel) and bool(offset)
    if limits is not None and offset:
        beyond = beyond_travel(analysis.bounds, offset, limits.travel)
    return Preflight(analysis, limits, beyond, checked)


@functools.lru_cache(maxsize=16)
def _analysis(
    path: Path,
    fingerprint: bytes,
    dialect: str,
    velocity: tuple[tuple[str, float], ...],
    acceleration: tuple[tuple[str, float], ...],
) -> Analysis:
    """A file's analysis, kept while the file holds the same bytes (`fingerprint`).

    Running one program on workpiece after workpiece analyses it once (hashing
    a file costs about a hundredth of analysing it); a file uploaded again with
    other bytes is analysed afresh.
    """
    del fingerprint  # part of the key only
    with path.open(encoding="utf-8", errors="replace") as f:
        return analyze(
            f,
            DIALECTS[dialect],
            velocity=dict(velocity) or None,
            acceleration=dict(acceleration) or None,
        )


def _recovery_line(job: Job) -> tuple[int, list[str]]:
    """Where `job` should resume, and what is unsure about that line.

    The resume line is `line_executed`: the line the board was running, which
    is run again from its start.
    """
    if job.kind != "make" or job.file is None:
        raise NotResumable(f"job {job.id} is a {job.kind} operation, not a make job")
    if job.state not in RESUMABLE:
        raise NotResumable(f"job {job.id} is {job.state}: only {', '.join(RESUMABLE)} resume")
    line = job.line_executed
    if line is None:
        about = "the board never said which line it ran: resuming at the job's start"
        return job.start_line or 1, [about]
    about = (
        f"line {line} is the last the board reported running, at most a status "
        f"interval before the stop; it answered lines up to {job.lines_acked} "
        "of the job's, so it may have gone further"
    )
    return line, [about]


async def plan_at(
    path: Path,
    line: int,
    dialect: str,
    *,
    board: Board | None,
    safe_z: float | None,
    dwell: float,
    plunge_feed: float | None = None,
    laser: bool = False,
) -> ResumePlan:
    """The plan to resume the file at `line` (or the first line to send after it), on a
    board that holds `board` (its stored offsets, G92 and speed, read just before)."""

    def run() -> ResumePlan:
        with path.open(encoding="utf-8", errors="replace") as f:
            plan = plan_resume(
                f,
                line,
                DIALECTS[dialect],
                board=board,
                safe_z=safe_z,
                dwell=dwell,
                plunge_feed=plunge_feed,
                laser=laser,
            )
        with path.open(encoding="utf-8", errors="replace") as f:
            first = next(program_lines(f, line), None)
        if first is None:
            raise ResumeError(f"nothing to run at or after line {line}")
        return plan if first[0] == line else _at(plan, first[0])

    try:
        return await asyncio.to_thread(run)
    except ResumeError as exc:
        raise NotResumable(str(exc)) from None
    except FileNotFoundError:
        raise NotResumable(f"the file {path.name!r} is gone") from None


def _at(plan: ResumePlan, line: int) -> ResumePlan:
    """The same plan, starting at the first sendable line (blank and comment lines skipped)."""
    return dataclasses.replace(plan, line=line)


# -- for one machine ----------------------------------------------------------


async def analyze_for(machine: Machine | None, path: Path) -> Preflight:
    """`path` against `machine`: its dialect, speeds and travel; without one, g2core's rules."""
    if machine is None:
        return await analyze_file(path, "g2core")
    limits = await _limits(machine)
    offset = work_offset(machine.snapshot())
    return await analyze_file(path, machine.config.dialect, limits, offset)


async def prepare_start(
    machine: Machine, path: Path, start_line: int, *, restore: bool, force: bool
) -> list[str] | None:
    """What a make job of `path` from `start_line` needs before it starts: the preamble.

    Refuses a program whose moves leave the machine's travel (OutOfTravel)
    unless `force`, when the check can run (the travel known, the machine
    homed). From `start_line` > 1 with `restore`, returns the resume
    plan's lines (the modal state restored, a safe approach) to send before
    the file's; else None.
    """
    limits = await _limits(machine) if not force or start_line > 1 else None
    offset = work_offset(machine.snapshot())
    if not force and limits is not None and limits.travel and offset:
        # Only a check that can run is worth reading the file for: the travel
        # is known and so is the work offset (the machine is homed).
        check = await analyze_file(path, machine.config.dialect, limits, offset)
        if check.beyond:
            raise OutOfTravel(
                f"{path.name} leaves {machine.id}'s travel: " + "; ".join(check.beyond),
                {"beyond_travel": check.beyond, "force": "true runs it anyway"},
            )
    if start_line > 1 and restore:
        return (await _plan(machine, path, start_line, limits)).lines
    return None


async def plan_for(machine: Machine, path: Path, line: int) -> ResumePlan:
    """The plan `prepare_start` would send to resume `path` at `line` on `machine`."""
    return await _plan(machine, path, line, await _limits(machine))


async def recovery_for(machine: Machine, path: Path, job: Job) -> tuple[ResumePlan, list[str]]:
    """Where `job` should resume on `machine`, and the plan that gets there safely.

    Returns the plan and what is unsure about its line (`_recovery_line`);
    NotResumable when the job or the file allows no safe resume.
    """
    line, about = _recovery_line(job)  # a job that cannot resume asks the board nothing
    return await _plan(machine, path, line, await _limits(machine)), about


async def _plan(
    machine: Machine, path: Path, line: int, limits: MachineLimits | None
) -> ResumePlan:
    """Resuming `path` at `line` on `machine`: from its safe height, with its dwell and
    plunge feed, in machine coordinates from the offsets its board holds now."""
    config = machine.config
    try:
        board = await machine.board_offsets()
    except MachineError as exc:
        raise NotResumable(
            f"{machine.id}: its board's offsets could not be read ({exc.message}): "
            "a resume is planned from them"
        ) from None
    laser = config.laser or machine.snapshot().get("laser_mode") is True
    return await plan_at(
        path,
        line,
        config.dialect,
        board=board,
        safe_z=machine.safe_height(limits),
        dwell=config.spindle_dwell,
        plunge_feed=config.plunge_feed,
        laser=laser,
    )


async def _limits(machine: Machine) -> MachineLimits | None:
    """The board's travel and speeds; None when it cannot say (not connected, refused)."""
    try:
        return await machine.limits()
    except MachineError as exc:
        log.info("machine limits not read", machine=machine.id, error=exc.message)
        return None
