"""What a make job needs before it starts: its checks, and a resume's preamble.

job.start's logic (api/methods/jobs.py): the file checked for lines the board
would refuse (preflight.check_file) and for moves that leave the travel
(preflight.analyze_file), and from a later line the resume plan's lines
(resumes.py) sent before the file's. The file's version is taken first: the
job streams the version its checks read, or nothing (jobfile.py).
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass
from pathlib import Path

from hostd.machine.guard import line_limit, numbers_lines, tool_change_policy
from hostd.machine.jobfile import Version, version_of
from hostd.machine.machine import Machine
from hostd.machine.preflight import (
    NotRunnable,
    OutOfTravel,
    analyze_file,
    check_file,
    work_offset,
)
from hostd.machine.resumes import plan_with
from hostd.machine.workers import WorkerPool


@dataclass(frozen=True, slots=True)
class Start:
    """What `prepare_start` found a make job needs."""

    preamble: list[str] | None  # a resume's lines, sent before the file's
    # The file's sendable lines from the start line, as the check counted them in its
    # pass over the file; None when no check ran (`force`): the job counts them itself.
    lines: int | None
    # The file as it was before the checks read it: the job streams this version or
    # nothing (`start_make`'s `version`; jobfile.py).
    version: Version
    # That version's SHA-256, if the travel check hashed it: the job's row keeps it, and
    # a start on a homed machine need not read the file a second time for it.
    sha256: str | None = None


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
    version = await asyncio.to_thread(version_of, path)
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
            version=version,
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
    limits = await machine.known_limits() if not force or start_line > 1 else None
    offset = work_offset(machine)
    digest = None
    if not force and limits is not None and limits.travel and offset:
        # Only a check that can run is worth reading the file for: the travel
        # is known and so is the work offset (the machine is homed).
        check = await analyze_file(
            path, machine.config.spec, limits, offset, pool=pool, version=version
        )
        digest = check.sha256
        if check.beyond:
            raise OutOfTravel(
                f"{path.name} leaves {machine.id}'s travel: " + "; ".join(check.beyond),
                {"beyond_travel": check.beyond, "force": "true runs it anyway"},
            )
    preamble = None
    if start_line > 1 and restore:
        preamble = (await plan_with(machine, path, start_line, limits, pool, version)).lines
    return Start(preamble, counted, version, digest)
