"""Before a job moves anything: its analysis against the machine, and a resume's plan.

The G-code rules are in `hostd.protocol.gcodestate` (the model, the analysis, the
resume plan) and the dialect's settings in its session (`limit_settings`,
`machine_limits`); this module reads the file off the event loop and puts them
together for one machine. Reading a file runs on the daemon's worker processes
(`workers.WorkerPool`), never in the daemon's interpreter: a hostile or huge
file costs a worker its time and memory limit, and the event loop nothing.
The functions that take a `Machine` (`analyze_for`,
`prepare_start`, `plan_for`, `recovery_for`) read what they need of it
themselves: its board's limits (none when the board cannot say), its work
offset, safe height and dwell.
"""

from __future__ import annotations

import asyncio
import dataclasses
import hashlib
from collections import OrderedDict
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import structlog

from hostd.machine.guard import line_limit, numbers_lines, tool_change_policy
from hostd.machine.jobstore import Job
from hostd.machine.machine import Machine
from hostd.machine.workers import WorkerPool
from hostd.protocol import dialects
from hostd.protocol.commands import MAX_LINE_BYTES
from hostd.protocol.dialects import DialectSpec
from hostd.protocol.errors import MachineError
from hostd.protocol.gcodestate import Analysis, analyze
from hostd.protocol.gcodestate import Dialect as GcodeDialect
from hostd.protocol.gcodestate.analysis import beyond_travel
from hostd.protocol.gcodestate.blocks import unsupported_text
from hostd.protocol.gcodestate.figures import DEFAULT_RAPID
from hostd.protocol.gcodestate.model import ProgramError
from hostd.protocol.gcodestate.resume import Board, ResumeError, ResumePlan, plan_resume
from hostd.protocol.gcodestate.state import MM_PER_INCH
from hostd.protocol.jobcheck import Findings, check_program
from hostd.protocol.limits import MachineLimits
from hostd.protocol.program import program_lines

log = structlog.get_logger(__name__)

RESUMABLE = ("interrupted", "failed", "cancelled")


class OutOfTravel(MachineError):
    """The program's moves leave the machine's travel (`force` to run it anyway).

    api.md's 1008 (the contract's code for it; it was 1010 before issue 24)."""

    code = 1008


class NotRunnable(MachineError):
    """Lines the board would refuse or must not run (`force` to start it anyway): 1008
    too, since a client handles it as the travel refusal (look, then force or fix)."""

    code = 1008


class NotResumable(MachineError):
    """No safe resume: the job, the file or the position does not allow one."""

    code = 1011


class BadProgram(MachineError):
    """A line of the file no board may run as written (a number that does not fit)."""

    code = 1012

    @classmethod
    def of(cls, path: Path, error: ProgramError) -> BadProgram:
        return cls(f"{path.name}, {error}", {"line": error.line, "reason": error.message})


# Analyses kept, by the file's digest, dialect and speeds (each is a few kilobytes:
# the model bounds its warnings and tools).
ANALYSES_KEPT = 16
_analyses: OrderedDict[tuple[object, ...], Analysis] = OrderedDict()


@dataclass(frozen=True, slots=True)
class Preflight:
    analysis: Analysis
    limits: MachineLimits | None
    beyond: list[str]  # why the program leaves the travel, axis by axis
    checked: bool = False  # the travel and the work offset were known: the check ran
    findings: Findings | None = None  # lines the board would refuse (jobcheck.py)
    dialect: str | None = None  # the G-code dialect's name the analysis ran with

    def to_json(self) -> dict[str, Any]:
        """file.analyze's answer: api.md's keys (`duration_s`, `warnings` as text) and ours.

        `warnings` is api.md's list of strings; `warning_details` has the same
        warnings as `{text, line, count}`. Without the machine's speeds the
        estimate uses DEFAULT_LIMITS_TEXT's defaults, and a warning says so.

        An `M6` is the machine's tool_change policy's to decide, not the dialect's
        (grbl's G-code table lacks M6, but the host holds the job there, or strips
        it): with the findings, the model's "M6 is not supported" is dropped and
        each M6 is said as the policy takes it: nothing under "pause" or "probe"
        (the job holds there), a "stripped" note under "ignore", a refusal under
        "refuse" or no policy (also in `problems`: job.start refuses the file).
        """
        a = self.analysis
        warnings = a.warnings
        if self.findings is not None and self.dialect is not None:
            m6 = unsupported_text("M6", self.dialect)
            warnings = tuple(w for w in warnings if w.text != m6)
        details = [{"text": w.text, "line": w.line, "count": w.count} for w in warnings]
        details += [{"text": text, "line": None, "count": 1} for text in self.beyond]
        if self.findings is not None:
            refused = [f for f in self.findings.found if f.kind == "tool-change"]
            details += [
                {"text": f"{f.text}: job.start refuses this file", "line": f.line, "count": 1}
                for f in refused
            ]
            # the M6s a machine's "ignore" policy strips
            details += [{"text": f.text, "line": f.line, "count": 1} for f in self.findings.notes]
        if self.limits is None or not self.limits.velocity:
            details.insert(0, {"text": DEFAULT_LIMITS_TEXT, "line": None, "count": 1})
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
            "duration_s": round(a.seconds, 3),
            "estimate": round(a.seconds, 3),
            "warnings": [_warning_text(w) for w in details],
            "warning_details": details,
            "beyond_travel": self.beyond,
            "travel_checked": self.checked,
            "limits": None if self.limits is None else self.limits.to_json(),
            "problems": [] if self.findings is None else [f.to_json() for f in self.findings.found],
            "problems_total": 0 if self.findings is None else self.findings.total,
        }


# The estimate's defaults where the machine's speeds are not known (no `machine`, or a
# board that did not say): GcodeModel's DEFAULT_RAPID, the program's own F, no acceleration.
DEFAULT_LIMITS_TEXT = (
    f"duration_s is estimated with default limits, not a machine's: rapids at"
    f" {DEFAULT_RAPID:g} mm/min, feed moves at the program's F, no acceleration"
    " (give a connected machine for its own speeds)"
)


def _warning_text(warning: dict[str, Any]) -> str:
    """One warning as api.md's string: where, what, and how often."""
    where = f"line {warning['line']}: " if warning["line"] else ""
    times = f" ({warning['count']} times)" if warning["count"] > 1 else ""
    return f"{where}{warning['text']}{times}"


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
    dialect: DialectSpec,
    limits: MachineLimits | None = None,
    offset: dict[str, float] | None = None,
    *,
    pool: WorkerPool,
) -> Preflight:
    """The file's figures, its estimate with the machine's speeds, and its travel check.

    Kept while the file holds the same bytes: running one program on workpiece
    after workpiece analyses it once (hashing a file costs about a hundredth of
    analysing it, and releases the GIL); a file uploaded again with other bytes
    is analysed afresh. BadProgram for a line no board may run; AnalysisLimit
    past the worker's limits.
    """

    def digest() -> bytes:
        with path.open("rb") as f:
            return hashlib.file_digest(f, "blake2b").digest()

    velocity = tuple(sorted(limits.velocity.items())) if limits else ()
    acceleration = tuple(sorted(limits.acceleration.items())) if limits else ()
    key = (path, await asyncio.to_thread(digest), dialect.name, velocity, acceleration)
    analysis = _analyses.get(key)
    if analysis is None:
        try:
            analysis = await pool.run(
                f"analysing {path.name}", _analysis, path, dialect.gcode, velocity, acceleration
            )
        except ProgramError as exc:
            raise BadProgram.of(path, exc) from None
        _analyses[key] = analysis
        while len(_analyses) > ANALYSES_KEPT:
            _analyses.popitem(last=False)
    else:
        _analyses.move_to_end(key)
    beyond: list[str] = []
    checked = limits is not None and bool(limits.travel) and bool(offset)
    if limits is not None and offset:
        beyond = beyond_travel(analysis.bounds, offset, limits.travel, analysis.bound_lines)
    return Preflight(analysis, limits, beyond, checked)


async def check_file(
    path: Path,
    dialect: DialectSpec,
    max_line_bytes: int,
    tool_change: str | None,
    start_line: int = 1,
    *,
    pool: WorkerPool,
    numbered: bool = True,
) -> Findings:
    """The lines of `path` (from `start_line`) the board would refuse or must not run;
    `numbered`: as the job writes them, each with its `N<line>` (`numbers_lines`)."""
    return await pool.run(
        f"checking {path.name}",
        _check_file,
        path,
        dialect,
        max_line_bytes,
        tool_change,
        start_line,
        numbered,
    )


def _check_file(
    path: Path,
    dialect: DialectSpec,
    max_line_bytes: int,
    tool_change: str | None,
    start_line: int,
    numbered: bool,
) -> Findings:
    """`check_file`'s work, on a worker process."""
    with path.open(encoding="utf-8", errors="replace") as f:
        return check_program(
            program_lines(f, start_line),
            dialect=dialect,
            max_line_bytes=max_line_bytes,
            tool_change=tool_change,
            numbered=numbered,
        )


def _analysis(
    path: Path,
    gcode: GcodeDialect,
    velocity: tuple[tuple[str, float], ...],
    acceleration: tuple[tuple[str, float], ...],
) -> Analysis:
    """A file's analysis: run on a worker process."""
    with path.open(encoding="utf-8", errors="replace") as f:
        return analyze(
            f,
            gcode,
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
) -> ResumePlan:
    """The plan to resume the file at `line` (or the first line to send after it), on a
    board that holds `board` (its stored offsets, G92 and speed, read just before)."""
    try:
        return await pool.run(
            f"planning a resume of {path.name}",
            _plan_file,
            path,
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
    except FileNotFoundError:
        raise NotResumable(f"the file {path.name!r} is gone") from None


def _plan_file(
    path: Path,
    line: int,
    gcode: GcodeDialect,
    board: Board | None,
    safe_z: float | None,
    dwell: float,
    plunge_feed: float | None,
    laser: bool,
) -> ResumePlan:
    """`plan_at`'s work, on a worker process."""
    with path.open(encoding="utf-8", errors="replace") as f:
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
    with path.open(encoding="utf-8", errors="replace") as f:
        first = next(program_lines(f, line), None)
    if first is None:
        raise ResumeError(f"nothing to run at or after line {line}")
    return plan if first[0] == line else _at(plan, first[0])


def _at(plan: ResumePlan, line: int) -> ResumePlan:
    """The same plan, starting at the first sendable line (blank and comment lines skipped)."""
    return dataclasses.replace(plan, line=line)


# -- for one machine ----------------------------------------------------------


async def analyze_for(machine: Machine | None, path: Path, *, pool: WorkerPool) -> Preflight:
    """`path` against `machine`: its dialect, speeds and travel; without one, the default
    dialect's rules (dialects.DEFAULT)."""
    if machine is None:
        spec = dialects.lookup(dialects.DEFAULT)
        found = await check_file(path, spec, MAX_LINE_BYTES + 1, None, pool=pool)
        analysed = await analyze_file(path, spec, pool=pool)
        return replace(analysed, findings=found, dialect=spec.gcode.name)
    limits = await _limits(machine)
    offset = work_offset(machine.snapshot())
    found = await check_file(
        path,
        machine.config.spec,
        line_limit(machine),
        tool_change_policy(machine),
        pool=pool,
        numbered=numbers_lines(machine),
    )
    analysis = await analyze_file(path, machine.config.spec, limits, offset, pool=pool)
    return replace(analysis, findings=found, dialect=machine.config.spec.gcode.name)


@dataclass(frozen=True, slots=True)
class Start:
    """What `prepare_start` found a make job needs."""

    preamble: list[str] | None  # a resume's lines, sent before the file's
    # The file's sendable lines from the start line, as the check counted them in its
    # pass over the file; None when no check ran (`force`): the job counts them itself.
    lines: int | None


async def prepare_start(
    machine: Machine,
    path: Path,
    start_line: int,
    *,
    restore: bool,
    force: bool,
    pool: WorkerPool,
    notes: list[str] | None = None,
) -> Start:
    """What a make job of `path` from `start_line` needs before it starts: the preamble,
    and the count of its lines if the check read them.

    `notes`, if given, gets what the job will do that the file does not say (the
    M6s a "ignore" policy strips), one line each, for job.start's `warnings`.

    Refuses a program whose moves leave the machine's travel (OutOfTravel)
    unless `force`, when the check can run (the travel known, the machine
    homed). From `start_line` > 1 with `restore`, returns the resume
    plan's lines (the modal state restored, a safe approach) to send before
    the file's; else None.
    """
    counted = None
    if not force:
        # Lines the board would refuse, or must not run: a job that would fail at its
        # 20,000th line for what the host can see now fails before anything moves.
        found = await check_file(
            path,
            machine.config.spec,
            line_limit(machine),
            tool_change_policy(machine),
            start_line,
            pool=pool,
            numbered=numbers_lines(machine),
        )
        if notes is not None:
            notes += [f"line {f.line}: {f.text}" for f in found.notes]
            if found.notes_total > len(found.notes):
                notes.append(f"and {found.notes_total - len(found.notes)} more M6 lines")
        if found:
            raise NotRunnable(
                f"{path.name} cannot run on {machine.id}: {found.summary()}",
                {
                    "problems": [f.to_json() for f in found.found],
                    "problems_total": found.total,
                    "force": "true starts it anyway",
                },
            )
        counted = found.lines
    limits = await _limits(machine) if not force or start_line > 1 else None
    offset = work_offset(machine.snapshot())
    if not force and limits is not None and limits.travel and offset:
        # Only a check that can run is worth reading the file for: the travel
        # is known and so is the work offset (the machine is homed).
        check = await analyze_file(path, machine.config.spec, limits, offset, pool=pool)
        if check.beyond:
            raise OutOfTravel(
                f"{path.name} leaves {machine.id}'s travel: " + "; ".join(check.beyond),
                {"beyond_travel": check.beyond, "force": "true runs it anyway"},
            )
    preamble = None
    if start_line > 1 and restore:
        preamble = (await _plan(machine, path, start_line, limits, pool)).lines
    return Start(preamble, counted)


async def plan_for(machine: Machine, path: Path, line: int, *, pool: WorkerPool) -> ResumePlan:
    """The plan `prepare_start` would send to resume `path` at `line` on `machine`."""
    return await _plan(machine, path, line, await _limits(machine), pool)


async def recovery_for(
    machine: Machine, path: Path, job: Job, *, pool: WorkerPool
) -> tuple[ResumePlan, list[str]]:
    """Where `job` should resume on `machine`, and the plan that gets there safely.

    Returns the plan and what is unsure about its line (`_recovery_line`);
    NotResumable when the job or the file allows no safe resume.
    """
    line, about = _recovery_line(job)  # a job that cannot resume asks the board nothing
    return await _plan(machine, path, line, await _limits(machine), pool), about


async def _plan(
    machine: Machine, path: Path, line: int, limits: MachineLimits | None, pool: WorkerPool
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
        config.spec,
        board=board,
        safe_z=machine.safe_height(limits),
        dwell=config.spindle_dwell,
        plunge_feed=config.plunge_feed,
        laser=laser,
        pool=pool,
    )


async def _limits(machine: Machine) -> MachineLimits | None:
    """The board's travel and speeds; None when it cannot say (not connected, refused)."""
    try:
        return await machine.limits()
    except MachineError as exc:
        log.info("machine limits not read", machine=machine.id, error=exc.message)
        return None
