"""The Machine's operations: make jobs, programs, jogs and settings batches, and
the board's settings, limits and offsets read for them.

A layer of `Machine` (machine.py lists the layers). Operations (`make`,
`jog`, `settings`) start only from idle, each recorded as a job row by the
job runner (jobrunner.py); `make` streams a file from the jobs directory and
is the only pausable one.
"""

from __future__ import annotations

import asyncio
import itertools
from collections.abc import Iterator
from typing import Any, TextIO

import structlog

from hostd.machine.jobfile import Version, open_text, sha256
from hostd.machine.jobstore import Job
from hostd.machine.machine_core import MachineCore
from hostd.machine.supervisor import Event as SupEvent
from hostd.protocol.commands import InvalidCommand
from hostd.protocol.errors import Busy, MachineError
from hostd.protocol.gcodestate.resume import Board
from hostd.protocol.limits import MachineLimits
from hostd.protocol.program import program_blocks, program_lines
from hostd.protocol.vocabulary import StreamEnd, StreamResult

log = structlog.get_logger(__name__)


class MachineOperations(MachineCore):
    """The operations a machine runs, and what they read from the board (see `Machine`)."""

    async def start_make(
        self,
        file: str,
        start_line: int = 1,
        preamble: list[str] | None = None,
        *,
        counted: int | None = None,
        version: Version | None = None,
        sha256: str | None = None,
    ) -> Job:
        """Stream a file of the jobs directory (its name is checked by the API layer).

        `preamble`: lines sent first, before `start_line` (a resume's restore and
        approach, hostd.protocol.gcodestate.resume); they are file line 0, and the row
        keeps them. Every line goes with its file line number as an N word. `counted`:
        the file's sendable lines from `start_line`, if the job's check just counted
        them on a worker (jobstart.prepare_start); else they are counted here.
        `version`: the file's version those checks read; another is not streamed
        (FileChanged, jobfile.py). `sha256`: that version's, if a check hashed it.
        """
        path = self.jobs_dir / file
        # NoSuchFile unless a regular file; FileChanged unless `version`, when given.
        handle = await asyncio.to_thread(open_text, path, version)
        try:
            digest, total = await asyncio.to_thread(_survey, handle, start_line, counted, sha256)
        except BaseException:
            handle.close()
            raise
        before = [(0, line) for line in preamble or ()]
        try:
            lines = itertools.chain(before, program_lines(handle, start_line))
            return await self._start_make(
                file,
                total + len(before),
                lines,
                handle,
                start_line=start_line if start_line > 1 or preamble else None,
                preamble=preamble,
                file_sha256=digest,
            )
        except BaseException:
            handle.close()
            raise

    async def start_program(self, lines: list[str]) -> Job:
        """Lines the daemon made (a macro's, a frame's), run as a make job with no file:
        admitted, numbered, paused, resumed and cancelled as any make job. The caller has
        checked the lines as a file's are checked (hostd/machine/macros.py)."""
        return await self._start_make(None, len(lines), enumerate(lines, start=1), None)

    async def _start_make(
        self,
        file: str | None,
        total: int,
        lines: Iterator[tuple[int, str]],
        handle: TextIO | None,
        *,
        start_line: int | None = None,
        preamble: list[str] | None = None,
        file_sha256: str | None = None,
    ) -> Job:
        """A make job, its M6s read by the tool-change policy (toolchange.py)."""
        lines = self.tools.lines(lines)
        holds = self.tools.holds(lines)
        job = await self.jobs.start(
            "make",
            file,
            total,
            lines,
            handle,
            start_line=start_line,
            preamble=preamble,
            holds=holds,
            file_sha256=file_sha256,
        )
        if holds is not None:
            self.tools.follow(self.jobs.live(), holds)
        return job

    async def jog(self, axes: dict[str, float], feed: float) -> Job:
        lines = self.engine.session.jog_lines(axes, feed)
        if self.tools.holding() and self.job is not None:
            if not self.tools.operator_may_move():
                raise Busy(f"{self.id} is measuring the new tool: wait until it is done")
            # A job waits at a tool change: the jog is its own lines, no operation of its own.
            self.tools.operator_acted()
            for line in lines:
                await self.engine.send(line, operation=True)
            return self.job
        # g2core jogs in G-code and puts G90 back as its last line; a stopped jog needs it too.
        restore = lines[-1] if len(lines) > 1 else None
        return await self.jobs.start(
            "jog", None, len(lines), enumerate(lines, start=1), None, if_stopped=restore
        )

    async def read_settings(self, keys: list[str]) -> dict[str, Any]:
        """Read settings: queries, so served in every state while the link is up; no job row."""
        session = self.engine.session
        lines = session.settings_read(keys)
        answers = await asyncio.gather(*(self.engine.send(line) for line in lines))
        return session.settings_found(keys, [response.body for response in answers])

    async def limits(self) -> MachineLimits:
        """Travel, traverse rates and accelerations, from the board's settings (its dialect's)."""
        session = self.engine.session
        return session.machine_limits(await self.read_settings(session.limit_settings()))

    async def known_limits(self) -> MachineLimits | None:
        """`limits`, or None when the board cannot say (not connected, refused): what a
        check, a plan or a tool change goes without."""
        try:
            return await self.limits()
        except MachineError as exc:
            log.info("machine limits not read", machine=self.id, error=exc.message)
            return None

    def positions_mm(self) -> tuple[dict[str, float], dict[str, float]]:
        """The machine and the work position as the board last reported them, in mm:
        each in the units its dialect reports it in (`position_scales`: g2core's `mpo`
        is always mm, its `pos` follows G20; grbl's both follow `$13`)."""
        machine_scale, work_scale = self.engine.session.position_scales()
        model = self.engine.model
        return (
            {a: v * machine_scale for a, v in model.machine_position.items()},
            {a: v * work_scale for a, v in model.position.items()},
        )

    async def board_offsets(self) -> Board:
        """The board's stored offsets (G54..), its G92 and spindle speed, in mm: what a
        resume plans from (hostd.protocol.gcodestate.resume). Queries: any state."""
        session = self.engine.session
        answers = await asyncio.gather(*(self.engine.send(q) for q in session.offset_reads()))
        return session.board_offsets([response.body for response in answers])

    def safe_height(self, limits: MachineLimits | None) -> float | None:
        """`safe_z` from the config, else the top of the Z travel (mm, machine coordinates).

        The travel's top is a place only once the machine is homed: before, machine
        coordinates count from wherever the board was switched on, and `G53 G0 Z<top>`
        could drive Z down to that height, or up into its end stop. Unhomed and without
        `safe_z`, the safe height is unknown (None), and whoever needs it refuses.
        """
        if self.config.safe_z is not None:
            return self.config.safe_z
        homed = self.engine.model.homed is True
        if homed and limits is not None and "z" in limits.travel:
            return limits.travel["z"][1]
        return None

    async def write_settings(
        self, values: dict[str, bool | int | float | str]
    ) -> tuple[Job, list[dict[str, Any]]]:
        """`settings` with the lines the board's dialect writes these values with."""
        return await self.settings(self.engine.session.settings_write(values))

    async def settings(self, lines: list[str]) -> tuple[Job, list[dict[str, Any]]]:
        """A batch of settings lines run as one operation; the bodies the board answered.

        The row says `completed` only when every line was answered with
        status 0; anything else, even the request being abandoned, is `failed`.
        """
        job = await self.jobs.begin("settings", None, len(lines))
        bodies: list[dict[str, Any]] = []
        result = StreamResult(StreamEnd.FAILED, 1005, "the settings operation was abandoned")
        try:
            for line in lines:
                response = await self.engine.send(line, operation=True)
                bodies.append(response.body)
                await self.jobs.save(lines_sent=len(bodies), lines_acked=len(bodies))
            result = StreamResult(StreamEnd.COMPLETED)
        except MachineError as exc:
            result = StreamResult(StreamEnd.FAILED, exc.code, exc.message)
            raise
        except InvalidCommand as exc:
            result = StreamResult(StreamEnd.FAILED, -32602, exc.message)
            raise
        finally:
            await asyncio.shield(self.jobs.end(result))
        return job, bodies

    def _begin_operation(self) -> None:
        """An operation may begin: a locked-out board is the first thing to say
        (204/205/206), then a fault (1007), then "busy" (1003, unless idle)."""
        self.engine.admit_action()
        self.refuse_if_faulted()
        self.supervisor.fire(SupEvent.START_OPERATION)

    def _operation_stopped(self) -> None:
        if self.supervisor.can(SupEvent.OPERATION_STOPPED):
            self.supervisor.fire(SupEvent.OPERATION_STOPPED)
        self._settle()


def _survey(
    handle: TextIO, start_line: int, counted: int | None, known: str | None
) -> tuple[str, int]:
    """The SHA-256 of the file open in `handle` (the row keeps it: a resume of the job
    must find these bytes; `known` if a check hashed the same version) and its sendable
    lines from `start_line` (`counted` if the check counted them), read from the one
    open file the job streams, which is left at its start again: whatever the name is
    now."""
    digest = known
    if digest is None:
        digest = sha256(handle.buffer)
        handle.seek(0)
    if counted is not None:
        return digest, counted
    count = sum(map(len, program_blocks(handle, start_line)))  # a block at a time, not a line
    handle.seek(0)
    return digest, count
