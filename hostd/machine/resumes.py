"""A job's resume: the line it resumes at, and the plan that gets there safely.

The plan's G-code rules are in `hostd.protocol.gcodestate.resume`; this module
reads the file on the daemon's worker processes (`workers.WorkerPool`, as
preflight.py does) and gives the plan what it needs of one machine, read
from it: its board's stored offsets and speeds, safe height, dwell and
plunge feed (`plan_for`, `recovery_for`; job.start's preamble,
jobstart.py). A lost job's resume plans from the bytes the job streamed or not
at all (`Job.file_sha256`): another program under its name would be run from
its middle on the job's workpiece.
"""

from __future__ import annotations

import asyncio
import dataclasses
from pathlib import Path

from hostd.machine.jobfile import (
    FileChanged,
    NoSuchFile,
    Version,
    file_version,
    open_binary,
    open_text,
    sha256,
)
from hostd.machine.jobstore import Job
from hostd.machine.machine import Machine
from hostd.machine.preflight import BadProgram
from hostd.machine.workers import WorkerPool
from hostd.protocol.dialects import DialectSpec
from hostd.protocol.errors import MachineError
from hostd.protocol.gcodestate import Dialect as GcodeDialect
from hostd.protocol.gcodestate.model import ProgramError
from hostd.protocol.gcodestate.resume import Board, ResumeError, ResumePlan, plan_resume
from hostd.protocol.limits import MachineLimits
from hostd.protocol.program import program_lines

RESUMABLE = ("interrupted", "failed", "cancelled")


class NotResumable(MachineError):
    """No safe resume: the job, the file or the position does not allow one."""

    code = 1011


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
        f"interval before the stop (or the M6 a tool change held the job at: every "
        f"line before it ran); it answered {job.lines_acked} of the job's lines, "
        "so it may have gone further"
    )
    return line, [about]


async def plan_at(
    path: Path,
    line: int,
    dialect: DialectSpec,
    *,
    board: Board | None,
    safe_z: float | None,
    dwell: float,
    plunge_feed: float | None = None,
    laser: bool = False,
    pool: WorkerPool,
    version: Version | None = None,
) -> ResumePlan:
    """The plan to resume the file at `line` (or the first line to send after it), on a
    board that holds `board` (its stored offsets, G92 and speed, read just before);
    `version`: of that version of the file, else FileChanged."""
    try:
        return await pool.run(
            f"planning a resume of {path.name}",
            _plan_file,
            path,
            version,
            line,
            dialect.gcode,
            board,
            safe_z,
            dwell,
            plunge_feed,
            laser,
        )
    except ResumeError as exc:
        raise NotResumable(str(exc)) from None
    except ProgramError as exc:
        raise BadProgram.of(path, exc) from None
    except FileChanged:
        raise  # a start's version replaced: 1004, as the start's other checks say it
    except NoSuchFile as exc:  # gone, or no longer a regular file: no safe resume (1011)
        raise NotResumable(exc.message) from None


def _plan_file(
    path: Path,
    version: Version | None,
    line: int,
    gcode: GcodeDialect,
    board: Board | None,
    safe_z: float | None,
    dwell: float,
    plunge_feed: float | None,
    laser: bool,
) -> ResumePlan:
    """`plan_at`'s work, on a worker process: the plan, and the line it starts at, read
    from one open file."""
    with open_text(path, version) as f:
        plan = plan_resume(
            f,
            line,
            gcode,
            board=board,
            safe_z=safe_z,
            dwell=dwell,
            plunge_feed=plunge_feed,
            laser=laser,
        )
        f.seek(0)
        first = next(program_lines(f, line), None)
    if first is None:
        raise ResumeError(f"nothing to run at or after line {line}")
    return plan if first[0] == line else _at(plan, first[0])


def _at(plan: ResumePlan, line: int) -> ResumePlan:
    """The same plan, starting at the first sendable line (blank and comment lines skipped)."""
    return dataclasses.replace(plan, line=line)


# -- for one machine ----------------------------------------------------------


async def plan_for(machine: Machine, path: Path, line: int, *, pool: WorkerPool) -> ResumePlan:
    """The plan `prepare_start` would send to resume `path` at `line` on `machine`."""
    return await plan_with(machine, path, line, await machine.known_limits(), pool)


async def recovery_for(
    machine: Machine, path: Path, job: Job, *, pool: WorkerPool
) -> tuple[ResumePlan, list[str]]:
    """Where `job` should resume on `machine`, and the plan that gets there safely.

    Returns the plan and what is unsure about its line (`_recovery_line`);
    NotResumable when the job or the file allows no safe resume.
    """
    line, about = _recovery_line(job)  # a job that cannot resume asks the board nothing
    version = await asyncio.to_thread(_ran_version, path, job)
    if job.file_sha256 is None:
        about.append(
            f"which version of {job.file} job {job.id} ran was not recorded (a job from "
            f"before 2026-11-29): check that the file is the one it ran"
        )
    limits = await machine.known_limits()
    return await plan_with(machine, path, line, limits, pool, version), about


def _ran_version(path: Path, job: Job) -> Version:
    """The version of `path` now, if it holds the bytes `job` streamed (or the job kept
    none to compare); else NotResumable: a resume of the job would run another program
    from the middle, on the job's workpiece."""
    try:
        with open_binary(path) as f:
            version = file_version(f)
            if job.file_sha256 is None:
                return version
            now = sha256(f)
    except NoSuchFile as exc:
        raise NotResumable(exc.message) from None
    if now != job.file_sha256:
        raise NotResumable(
            f"{job.file} is not the file job {job.id} ran: it changed since (another "
            "upload?). To resume this version, plan it from its file and a line"
        )
    return version


async def plan_with(
    machine: Machine,
    path: Path,
    line: int,
    limits: MachineLimits | None,
    pool: WorkerPool,
    version: Version | None = None,
) -> ResumePlan:
    """Resuming `path` (`version` of it, if given) at `line` on `machine`: from its safe
    height, with its dwell and plunge feed, in machine coordinates from the offsets its
    board holds now."""
    config = machine.config
    try:
        board = await machine.board_offsets()
    except MachineError as exc:
        raise NotResumable(
            f"{machine.id}: its board's offsets could not be read ({exc.message}): "
            "a resume is planned from them"
        ) from None
    return await plan_at(
        path,
        line,
        config.spec,
        board=board,
        safe_z=machine.safe_height(limits),
        dwell=config.spindle_dwell,
        plunge_feed=config.plunge_feed,
        laser=machine.is_laser(),
        pool=pool,
        version=version,
    )
