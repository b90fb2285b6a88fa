"""Before a job moves anything: its analysis against the machine.

The G-code rules are in `hostd.protocol.gcodestate` (the model, the analysis)
and `hostd.protocol.jobcheck` (the lines a board would refuse), and the
dialect's settings in its session (`limit_settings`, `machine_limits`); this
module reads the file off the event loop and puts them together for one
machine. Reading a file runs on the daemon's worker processes
(`workers.WorkerPool`), never in the daemon's interpreter: a hostile or huge
file costs a worker its time and memory limit, and the event loop nothing.
`analyze_for` reads what it needs of a `Machine` itself: its board's limits
(none when the board cannot say) and its work offset.

A job's start (`jobstart.py`) and a resume's plan (`resumes.py`) build on this.
"""

from __future__ import annotations

import asyncio
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from hostd.machine.guard import line_limit, numbers_lines, tool_change_policy
from hostd.machine.jobfile import Version, open_binary, open_text, sha256, version_of
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
from hostd.protocol.jobcheck import Findings, check_program
from hostd.protocol.limits import MachineLimits
from hostd.protocol.program import program_lines


class OutOfTravel(MachineError):
    """The program's moves leave the machine's travel (`force` to run it anyway).

    api.md's 1008 (the contract's code for it; it was 1010 before issue 24)."""

    code = 1008


class NotRunnable(MachineError):
    """Lines the board would refuse or must not run (`force` to start it anyway): 1008
    too, since a client handles it as the travel refusal (look, then force or fix)."""

    code = 1008


class BadProgram(MachineError):
    """A line of the file no board may run as written (a number that does not fit)."""

    code = 1012

    @classmethod
    def of(cls, path: Path, error: ProgramError) -> BadProgram:
        return cls(f"{path.name}, {error}", {"line": error.line, "reason": error.message})


# The axes a frame traces (`operations.frame`): a program's XY box.
FRAMED = ("x", "y")

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
    # `beyond` for the program's X and Y only: where its frame (`machine.frame`, the XY
    # box, Z never lowered) would leave the travel
    frame_beyond: list[str] = field(default_factory=list)
    sha256: str | None = None  # the bytes analysed (the version read): a job keeps it

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
            "frame_beyond_travel": self.frame_beyond,
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


def work_offset(machine: Machine) -> dict[str, float] | None:
    """Machine minus work position (mm) as the board reports them: the offset in force.

    None until the machine is homed: machine coordinates mean nothing before (a board
    counts from wherever it was switched on), so neither does a travel check. Each
    position in mm as its dialect reports it (`Machine.positions_mm`): until 2026-11-29
    both were scaled by the units mode, where g2core's machine position is always mm
    and grbl's positions follow `$13`, not G20: on a board left in G20 the check was
    off by up to 25 times the machine position.
    """
    if machine.engine.model.homed is not True:
        return None
    here, work = machine.positions_mm()
    return {a: here[a] - work[a] for a in here if a in work}


async def analyze_file(
    path: Path,
    dialect: DialectSpec,
    limits: MachineLimits | None = None,
    offset: dict[str, float] | None = None,
    *,
    pool: WorkerPool,
    version: Version | None = None,
) -> Preflight:
    """The file's figures, its estimate with the machine's speeds, and its travel check.

    Kept while the file holds the same bytes: running one program on workpiece
    after workpiece analyses it once (hashing a file costs about a hundredth of
    analysing it, and releases the GIL); a file uploaded again with other bytes
    is analysed afresh. The hash and the analysis read one version of the file
    (`version`, or the one there now), else FileChanged: an analysis is never
    kept under another version's bytes. BadProgram for a line no board may run;
    AnalysisLimit past the worker's limits.
    """
    if version is None:
        version = await asyncio.to_thread(version_of, path)

    def digest() -> str:
        with open_binary(path, version) as f:
            return sha256(f)

    velocity = tuple(sorted(limits.velocity.items())) if limits else ()
    acceleration = tuple(sorted(limits.acceleration.items())) if limits else ()
    file_sha256 = await asyncio.to_thread(digest)
    key = (path, file_sha256, dialect.name, velocity, acceleration)
    analysis = _analyses.get(key)
    if analysis is None:
        try:
            analysis = await pool.run(
                f"analysing {path.name}",
                _analysis,
                path,
                version,
                dialect.gcode,
                velocity,
                acceleration,
            )
        except ProgramError as exc:
            raise BadProgram.of(path, exc) from None
        _analyses[key] = analysis
        while len(_analyses) > ANALYSES_KEPT:
            _analyses.popitem(last=False)
    else:
        _analyses.move_to_end(key)
    beyond: list[str] = []
    frame_beyond: list[str] = []
    checked = limits is not None and bool(limits.travel) and bool(offset)
    if limits is not None and offset:
        bounds, lines = analysis.bounds, analysis.bound_lines
        beyond = beyond_travel(bounds, offset, limits.travel, lines)
        box = {axis: bounds[axis] for axis in FRAMED if axis in bounds}
        frame_beyond = beyond_travel(box, offset, limits.travel, lines)
    return Preflight(
        analysis, limits, beyond, checked, frame_beyond=frame_beyond, sha256=file_sha256
    )


async def check_file(
    path: Path,
    dialect: DialectSpec,
    max_line_bytes: int,
    tool_change: str | None,
    start_line: int = 1,
    *,
    pool: WorkerPool,
    numbered: bool = True,
    version: Version | None = None,
) -> Findings:
    """The lines of `path` (from `start_line`) the board would refuse or must not run;
    `numbered`: as the job writes them, each with its `N<line>` (`numbers_lines`);
    `version`: of that version of the file, else FileChanged."""
    return await pool.run(
        f"checking {path.name}",
        _check_file,
        path,
        version,
        dialect,
        max_line_bytes,
        tool_change,
        start_line,
        numbered,
    )


def _check_file(
    path: Path,
    version: Version | None,
    dialect: DialectSpec,
    max_line_bytes: int,
    tool_change: str | None,
    start_line: int,
    numbered: bool,
) -> Findings:
    """`check_file`'s work, on a worker process."""
    with open_text(path, version) as f:
        return check_program(
            program_lines(f, start_line),
            dialect=dialect,
            max_line_bytes=max_line_bytes,
            tool_change=tool_change,
            numbered=numbered,
        )


def _analysis(
    path: Path,
    version: Version,
    gcode: GcodeDialect,
    velocity: tuple[tuple[str, float], ...],
    acceleration: tuple[tuple[str, float], ...],
) -> Analysis:
    """A file's analysis: run on a worker process."""
    with open_text(path, version) as f:
        return analyze(
            f,
            gcode,
            velocity=dict(velocity) or None,
            acceleration=dict(acceleration) or None,
        )


# -- for one machine ----------------------------------------------------------


async def analyze_for(machine: Machine | None, path: Path, *, pool: WorkerPool) -> Preflight:
    """`path` against `machine`: its dialect, speeds and travel; without one, the default
    dialect's rules (dialects.DEFAULT). The check and the analysis read one version of
    the file, else FileChanged."""
    version = await asyncio.to_thread(version_of, path)
    if machine is None:
        spec = dialects.lookup(dialects.DEFAULT)
        found = await check_file(path, spec, MAX_LINE_BYTES + 1, None, pool=pool, version=version)
        analysed = await analyze_file(path, spec, pool=pool, version=version)
        return replace(analysed, findings=found, dialect=spec.gcode.name)
    limits = await machine.known_limits()
    offset = work_offset(machine)
    found = await check_file(
        path,
        machine.config.spec,
        line_limit(machine),
        tool_change_policy(machine),
        pool=pool,
        numbered=numbers_lines(machine),
        version=version,
    )
    analysis = await analyze_file(
        path, machine.config.spec, limits, offset, pool=pool, version=version
    )
    return replace(analysis, findings=found, dialect=machine.config.spec.gcode.name)
