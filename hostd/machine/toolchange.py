"""A job's tool changes (issue 29): the machine's `tool_change` policy at each `M6`.

- "pause": the job stops handing out lines before the M6 line, lets the board run
  what it already has (every line answered, then a status report read after that
  says it rests), stops the spindle if it is on (`M5`, the board at rest after
  it: a spindle left running while the operator's hands are at the tool is
  dangerous), and holds: supervisor `paused`, job `paused`, the snapshot's
  `tool_change` names the tool and the line. The operator may jog (`machine.jog`)
  and send lines (`machine.send`) while it holds: they go as the job's own
  operation lines, through the same command-class admission as any line.
  `job.tool_change_done` turns the spindle back on as the job has it once the M6
  line runs (`Modes`: M3/M4 and its S, the line's own words first: `T2 M5 M6`
  leaves it off, `T2 M6 M4 S900` turns it on CCW at 900), gives it
  `spindle_dwell` (none on a laser),
  records the change in the job's `tool_changes` and lets the job go on with
  the M6 line as its session sends it
  (`SessionBase.tool_change_line`: grbl without the M6, g2core as written).
- "probe": the same, and before the job goes on the new tool is measured on the
  fixed sensor (`[machines.probe] tool_sensor`): in mm and absolute, up to the
  safe height, over the sensor, no length offset (G49), G38.2 down at the probe
  feed within `max_travel`; the difference to the job's first measurement (its
  reference: the first tool change of a job measures it) becomes the tool length
  offset (`SessionBase.tool_length_lines`); then back over where it was, at the
  safe height, and the program's units, distance mode and feed as they were at
  the M6 (`Modes`, read from its lines). A sensor not touched is 1005 and the job
  keeps waiting (answer again, or cancel).
  The modes put back (`Modes.lines`, one line that moves nothing): units, distance
  mode, feed, and where the program's words set them, plane, coordinate system and
  motion mode (the measuring ends in `G53 G0` moves: a job's next `X3` would
  otherwise be a rapid). A G2/G3 in force comes back as G1 (no firmware selects an
  arc without moving), a G38.x not at all. The spindle comes back as for "pause".
  Under "pause" the same line is sent at the answer if the operator jogged or sent
  lines while it held (they run as the job's own).
- "ignore": the M6 is stripped as the lines are read (a warning in the log, and in
  job.start's and file.analyze's warnings, hostd/protocol/jobcheck.py).
- "refuse" (or no policy): job.start refuses the file (jobcheck.py).

The job's line source is wrapped (`ToolChangeLines`), which notes each M6
line (`marks`); the job's stream feeds each noted line to the session as a
hold point (hostd/protocol/stream.py, `feed(..., hold=True)`): when its turn
comes the session hands out nothing more and says so (`Stream.held`), and no
dialect's pump takes it for an underflow. The session passes it only when
told (`release_stream`), which only `job.tool_change_done` does. A user's
pause and resume (`!`/`~`) are the stream's `paused`, apart from the hold,
so `job.resume` can never carry the job past an M6 the operator has not
answered.

A cancel while it holds ends the job (`cancelled`) as any cancel does; a lost
link or a daemon stopped while it holds leaves the job `interrupted`, resumable
with job.recovery (its `tool_changes` so far are on disk). While it holds, the
job's `line_executed` is the M6 line (`JobStream.waits_at`): the board ran every
line before it, so job.recovery plans the resume there, as the next line to run.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import structlog

from hostd.machine.jobstore import ToolChange, now
from hostd.machine.rest import at_rest
from hostd.machine.stream import JobStream
from hostd.protocol.errors import Busy, ControllerError, MachineError
from hostd.protocol.toolchange import Modes, has_m6, tool_words, without_m6

if TYPE_CHECKING:
    from hostd.machine.machine import Machine

log = structlog.get_logger(__name__)

HOLDS = ("pause", "probe")  # the policies that hold the job at an M6
STRIPS = ("pause", "probe", "ignore")  # the policies under which a job may hold M6s at all
ANSWER_WAIT = 10.0
MOVE_WAIT = 600.0  # the probe cycle's moves, from anywhere on the table


class ToolChangeLines:
    """A job's (file line, text) pairs, with each M6 line noted (`marks`) and rewritten."""

    def __init__(
        self,
        lines: Iterator[tuple[int, str]],
        policy: str,
        rewrite: Callable[[str, int | None], str],
        machine_id: str,
    ) -> None:
        self._lines = lines
        self.policy = policy
        self._rewrite = rewrite
        # file line -> the tool its M6 loads, and the program's modes there
        self.marks: dict[int, Mark] = {}
        self.stripped = 0  # M6s the "ignore" policy took out
        self._tool: int | None = None  # the last T word read
        self._modes = Modes()
        self._log = log.bind(machine=machine_id)

    def __iter__(self) -> ToolChangeLines:
        return self

    def __next__(self) -> tuple[int, str]:
        number, text = next(self._lines)
        selected = tool_words(text)
        if selected:
            self._tool = selected[-1]
        modes = self._modes
        self._modes = modes.after(text)
        if not has_m6(text):
            return number, text
        tool = self._tool
        if self.policy in HOLDS:
            # The modes before the line (it runs after the change); the spindle as the line
            # leaves it: its own M3/M4/M5 and S are what the program wants once it runs.
            self.marks[number] = Mark(tool, modes, self._modes)
            return number, self._rewrite(text, tool)
        self.stripped += 1
        self._log.warning("M6 ignored (tool_change = ignore)", line=number, tool=tool)
        return number, without_m6(text) or self._rewrite(text, tool)


@dataclass(frozen=True, slots=True)
class Mark:
    """A job's M6 line, as its lines were read: the tool it loads, the program's modes
    before it (`before`), and after it (`after`: the spindle the answer turns back on,
    so that `T2 M5 M6` is not spun up only to be stopped, nor `T2 M6 M4` run clockwise
    first)."""

    tool: int | None
    before: Modes = field(default_factory=Modes)
    after: Modes = field(default_factory=Modes)


@dataclass(frozen=True, slots=True)
class Waiting:
    """The change the job holds for: at file line `line`, its M6 as read (`Mark`)."""

    line: int
    mark: Mark

    def to_json(self) -> dict[str, Any]:
        return {"tool": self.mark.tool, "line": self.line}


class ToolChanger:
    """One machine's tool changes: the job it follows, and the change it waits for."""

    def __init__(self, machine: Machine) -> None:
        self.machine = machine
        self.stream: JobStream | None = None
        self.marks: dict[int, Mark] = {}  # the followed job's M6 lines
        self.waiting: Waiting | None = None
        self.reference: float | None = None  # the first tool's probed Z (machine, mm)
        self._answering = False
        self._acted = False  # the operator jogged or sent a line while the job held
        self._log = log.bind(machine=machine.id)

    @property
    def policy(self) -> str | None:
        return self.machine.config.tool_change

    def lines(self, lines: Iterator[tuple[int, str]]) -> Iterator[tuple[int, str]]:
        """A make job's lines, read for their M6s when the policy acts on them."""
        if self.policy not in STRIPS:
            return lines
        session = self.machine.engine.session
        return ToolChangeLines(lines, str(self.policy), session.tool_change_line, self.machine.id)

    @staticmethod
    def holds(lines: Iterator[tuple[int, str]]) -> dict[int, Mark] | None:
        """The file lines a job of these lines holds before (filled as they are read)."""
        if not isinstance(lines, ToolChangeLines) or lines.policy not in HOLDS:
            return None
        return lines.marks

    def follow(self, stream: JobStream | None, marks: dict[int, Mark]) -> None:
        """Follow a job that holds at its M6s, in the machine's task group."""
        if stream is None:
            return
        self.stream = stream
        self.marks = marks
        self.waiting = None
        self.reference = None
        self.machine.jobs.follow_also(self._follow(stream), f"{self.machine.id}-job-tools")

    # -- holding --------------------------------------------------------------

    async def _follow(self, stream: JobStream) -> None:
        """Each time the session holds at a marked line: let the board finish, then hold."""
        try:
            while not stream.done:
                await _first(stream.reached.wait(), stream.result)
                if stream.done:
                    return
                stream.reached.clear()
                line = stream.held
                if line is None:
                    continue
                mark = self.marks.pop(line, Mark(None))
                await self._board_done(stream)
                if stream.done or stream.held != line:
                    return
                await self._spindle_off(mark.before)
                if stream.done:
                    return
                self._acted = False
                self.waiting = Waiting(line, mark)
                stream.waits_at(line)  # a lost link from now on resumes at the M6
                self._log.info("tool change: waiting for the operator", line=line, tool=mark.tool)
                self.machine.tool_change_held()
                await _first(self._answered(stream), stream.result)
        except MachineError as exc:  # the link went: the stream ends interrupted with it
            self._log.info("tool changes no longer followed", reason=exc.message)
        finally:
            if self.stream is stream:
                self.waiting = None

    async def _answered(self, stream: JobStream) -> None:
        # The answer releases the hold, and the very next line may hold again in the same
        # step: the waiting record, cleared by the answer, is what tells.
        await self.machine.engine.wait_for(lambda: stream.done or self.waiting is None)

    async def _board_done(self, stream: JobStream) -> None:
        """Every line sent is answered, and a report read after that says the board rests."""
        engine = self.machine.engine
        model = engine.model

        def answered() -> bool:
            return stream.done or stream.acked + stream.rejected + stream.discarded >= stream.sent

        await engine.wait_for(answered)
        while not stream.done:
            asked = model.reports
            engine.query_status()
            await engine.wait_for(
                lambda asked=asked: (
                    stream.done  # type: ignore[misc]
                    or (model.reports > asked and model.state is not None)
                )
            )
            if stream.done:
                return
            state = model.state
            if state is not None and state.is_resting and not model.hold:
                return
            # Still moving (or held by the user): wait for the next change, then ask again.
            seen = model.reports
            await engine.wait_for(lambda seen=seen: stream.done or model.reports > seen)  # type: ignore[misc]

    # -- the operator's answer ------------------------------------------------

    async def done(self) -> None:
        """job.tool_change_done: record the change (measured, under "probe") and go on."""
        stream, waiting = self.stream, self.waiting
        if stream is None or stream.done or waiting is None:
            raise Busy(f"{self.machine.id} is not waiting for a tool change")
        if self._answering:
            raise Busy(f"{self.machine.id}: the tool change is already being answered")
        state = self.machine.engine.model.state
        if state is None or not state.is_resting:
            name = state.name if state is not None else "an unknown state"
            raise Busy(f"{self.machine.id} is in {name}: let it come to rest first")
        self._answering = True
        try:
            if self.policy == "probe":
                await self._measure(waiting)  # puts the program's modes back itself
            elif self._acted:
                # The operator's lines ran as the job's (a g2core jog is `G91 G1 .. F..`
                # then `G90`): the program's modes back before its next line.
                await self._run(waiting.mark.before.lines(), lambda: True)
            if stream.done:
                raise Busy(f"{self.machine.id}: the job ended during the tool change")
            await self._spindle_back(waiting.mark.after)
            if stream.done:
                raise Busy(f"{self.machine.id}: the job ended during the tool change")
            change = ToolChange(tool=waiting.mark.tool, line=waiting.line, at=now())
            self.waiting = None
            self.machine.tool_change_answered(stream, change)
        finally:
            self._answering = False

    # -- the spindle: off while the operator's hands are at it ------------------

    async def _spindle_off(self, modes: Modes) -> None:
        """M5, and the board at rest after it, before the operator is told to change the
        tool: the job's spindle on (as its lines say), or the board's (as it reports)."""
        reported = (self.machine.engine.model.spindle or {}).get("state")
        if modes.spinning or reported in ("cw", "ccw"):
            self._log.info("tool change: spindle off", spindle=modes.spindle, reported=reported)
            await self._run(["M5"], lambda: True)

    async def _spindle_back(self, modes: Modes) -> None:
        """The spindle as the job has it once its M6 line ran (M3/M4 and its S: the
        line's own words, else as before it), then the machine's `spindle_dwell` for
        it to reach its speed (none on a laser: no spin-up)."""
        dwell = 0.0 if self.machine.is_laser() else self.machine.config.spindle_dwell
        lines = modes.spindle_lines(dwell)
        if lines:
            self._log.info("tool change: spindle back on", lines=lines)
            await self._run(lines, lambda: True)

    # -- "probe": the tool length on the fixed sensor --------------------------

    async def _measure(self, waiting: Waiting) -> None:
        """Up to the safe height, over the sensor, G38.2 down, the offset, and back.

        The first measurement of the job is its reference: the tool the job set up
        with. Each later one sets the tool length offset to its difference.
        """
        machine = self.machine
        config = machine.config.probe
        assert config is not None and config.tool_sensor is not None  # the config insists
        engine = machine.engine
        session = engine.session
        safe = machine.safe_height(await machine.known_limits())
        if safe is None:
            raise Busy(
                f"{machine.id}: no safe height known to reach the tool sensor: set safe_z, "
                "or home the machine (the Z travel's top means nothing before)"
            )
        start = self._machine_position()
        # Never down before crossing: where the job left the tool above the safe height
        # (its own clearance), it crosses there, as a frame does.
        safe = max(safe, start.get("z", safe))
        sensor = config.tool_sensor
        await self._run(
            [
                "G21 G90",  # the moves below are in mm, absolute
                f"G53 G0 Z{_n(safe)}",
                f"G53 G0 X{_n(sensor.x)} Y{_n(sensor.y)}",
                "G49",  # no length offset while measuring: each one is taken alike
            ],
            lambda: self._at(x=sensor.x, y=sensor.y, z=safe),
        )
        before = engine.model.probe
        await self._run(
            [f"G91 G38.2 Z-{_n(config.max_travel)} F{_n(config.feed)}", "G90"],
            lambda: engine.model.probe is not before,
        )
        probe = engine.model.probe
        if probe is before or not probe or not probe.get("ok"):
            raise ControllerError(0, f"{machine.id}: the tool sensor was not touched")
        touched = float(probe["position"]["z"])
        if self.reference is None:
            self.reference = touched
        delta = touched - self.reference
        mark = waiting.mark
        self._log.info("tool measured", tool=mark.tool, z=touched, offset=delta)
        back = [f"G53 G0 Z{_n(safe)}"]
        there: dict[str, float] = {"z": safe}
        if "x" in start and "y" in start:
            back.append(f"G53 G0 X{_n(start['x'])} Y{_n(start['y'])}")
            there.update(x=start["x"], y=start["y"])
        await self._run(
            [*session.tool_length_lines(mark.tool or 1, delta), *back, *mark.before.lines()],
            lambda: self._at(**there),
        )

    def _machine_position(self) -> dict[str, float]:
        """Machine mm, as the moves here are written (`G21`), whatever the board reports in."""
        return self.machine.positions_mm()[0]

    def _at(self, **where: float) -> bool:
        """The board stands there (machine mm, to the reports' 0.001)."""
        here = self._machine_position()
        return all(a in here and abs(here[a] - v) < 0.002 for a, v in where.items())

    async def _run(self, lines: list[str], there: Callable[[], bool]) -> None:
        """The job's own lines, each answered, then until a report after them says the
        board rests and `there` holds (a board answers a move as it queues it, and may
        report rest before its planner starts)."""
        engine = self.machine.engine
        for line in lines:
            await engine.send(line, timeout=ANSWER_WAIT, operation=True)
        # The job's stream is open, held at the M6: rest.py's in-job rule.
        await at_rest(
            self.machine, there, timeout=MOVE_WAIT, what="measuring the tool", in_job=True
        )

    # -- views ----------------------------------------------------------------

    def snapshot(self) -> dict[str, Any] | None:
        """The snapshot's `tool_change`: null, or the tool and line the job waits at."""
        waiting = self.waiting
        return None if waiting is None else waiting.to_json()

    def holding(self) -> bool:
        """A job waits at a tool change (while it is measured too)."""
        return self.waiting is not None and self.stream is not None and not self.stream.done

    def operator_acted(self) -> None:
        """A jog or a line of the operator's goes to the board as the job's: the modes
        it may change are put back at the answer (`done`)."""
        self._acted = True

    def operator_may_move(self) -> bool:
        """The operator's jogs and lines fit: it holds, and no measuring is under way
        (a line of theirs must not land between the probe's)."""
        return self.holding() and not self._answering


async def _first(*aws: Any) -> None:
    """Until the first of these is done; the others are cancelled (never a future we share)."""
    tasks = [a if isinstance(a, asyncio.Future) else asyncio.ensure_future(a) for a in aws]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in tasks:
            if isinstance(task, asyncio.Task):
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task


def _n(value: float) -> str:
    text = f"{value:.4f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text
