"""The operator's day (issue 29), first slice: home, set work zero, go to zero, spindle, overrides.

Each operation is lines a client could have typed into `machine.send`, sent the
same way (`Engine.send`), so the session's command-class admission judges them
exactly as any line: nothing reaches the board that a line would not. Before the
first line the supervisor must be idle (1003 otherwise), unless the board is in a
lockout: then the command class decides, which gives 204/205/206, or lets grbl's
`$H` through in ALARM (gnea/grbl system.c: `$H` is one of the two commands
ALARM accepts). One operation at a time per machine: a second one is 1003.

An operation that moves the machine or powers its spindle or beam (home, go to
zero, spindle on, a laser's test-fire, probe) is refused with 1007 while a fault
that blocks a job is active and not overridden, as a job and a jog are: a lid
open on a laser must not let the beam be fired from the dashboard. Setting work
zero moves nothing and turning the spindle off only makes safe: those are not
refused (docs/operations.md, "Faults"). Such a fault that becomes active while
one of them runs stops it as it stops a job: the board gets the dialect's job
kill, and the operation ends with 1007.

Why not a job row (like a jog)? api.md fixes the job kinds to make/jog/settings,
and these are single commands an operator gives, as `machine.send` is; the
history of what moved the machine is its console.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable, Mapping
from pathlib import Path
from typing import Any, Final

import structlog

from hostd.machine import macros, rest
from hostd.machine.jobstore import Job
from hostd.machine.machine import Machine
from hostd.machine.preflight import OutOfTravel, analyze_for
from hostd.machine.supervisor import State as SupState
from hostd.machine.workers import WorkerPool
from hostd.protocol.commands import InvalidCommand
from hostd.protocol.errors import Busy, ControllerError, ControllerTimeout, NotConnected
from hostd.protocol.gcode import axes_words, short_number
from hostd.protocol.gcodestate.state import MM_PER_INCH
from hostd.protocol.refusals import Refusal
from hostd.protocol.states import MachineState

log = structlog.get_logger(__name__)

# A homing cycle may take this long before the operation gives up waiting (the
# board goes on: a feedhold or reset stops it). grbl's own bound is its session's.
HOMING_WAIT: Final = 300.0
MOVE_WAIT: Final = 600.0  # a go-to-zero's moves, from anywhere on the table at a slow rapid
ANSWER_WAIT: Final = 10.0
AT_ZERO: Final = 0.001  # mm (or in): the reports' resolution, three decimals

_running: set[str] = set()  # machines with an operation of this module under way


@contextlib.asynccontextmanager
async def _operation(
    machine: Machine, *, powered: bool = True, fault_first: bool = False
) -> AsyncIterator[None]:
    """Admit one operation: connected, idle (or locked out: the command class decides);
    and, if it moves the machine or powers its spindle or beam (`powered`), no fault
    that blocks a job (1007, as for a job or a jog). In a lockout its code comes first,
    at a line, unless `fault_first`: the request a lockout may take (homing)."""
    state = machine.supervisor.state
    if state is SupState.DISCONNECTED or not machine.engine.ready:
        raise NotConnected(f"{machine.id} is not connected")
    if machine.id in _running:
        raise Busy(f"{machine.id} is already running an operation")
    locked = machine.engine.session.locked()
    if not locked and state is not SupState.IDLE:
        raise Busy(f"{machine.id} is {state.value}: wait until it is idle")
    if powered and (fault_first or not locked):
        machine.refuse_if_faulted()
    _running.add(machine.id)
    if powered:  # a fault that becomes active stops it (MachineCore._stop_powered_operation)
        machine.powered_operation = asyncio.current_task()
    try:
        await modes_known(machine)
        yield
    except BaseException:
        _stopped_for_fault(machine)
        raise
    else:
        _stopped_for_fault(machine)  # its waits swallowed the cancel: it still failed
    finally:
        machine.powered_operation = machine.operation_fault = None
        _running.discard(machine.id)


def _stopped_for_fault(machine: Machine) -> None:
    """The operation was stopped by a fault that became active (the board killed, its
    task cancelled): it ends with that 1007, not with the cancel or the error that the
    kill made of its line or its wait."""
    fault = machine.operation_fault
    if fault is None:
        return
    task = asyncio.current_task()
    if task is not None and task.cancelling():
        task.uncancel()  # the cancel was ours, and is answered by the 1007
    raise fault from None


async def modes_known(machine: Machine) -> None:
    """Until the modes the model shows are the board's: a poll of them in flight is
    answered first (grbl's `$G` after a client's line, `modes_pending`; the machine is
    idle meanwhile, since a query keeps it quiet). A jog's bound, a go-to-zero's lift
    and a frame's lines are written in the units and distance mode in force: a `G20`
    not read yet would have inches taken for millimetres."""
    engine = machine.engine
    session = engine.session
    if not session.modes_pending():
        return
    try:
        async with asyncio.timeout(ANSWER_WAIT):
            await engine.wait_for(lambda: not session.modes_pending())
    except TimeoutError:
        raise ControllerTimeout(f"{machine.id}: its modes were not answered") from None


async def home(machine: Machine, axes: list[str] | None) -> None:
    """Home; return once the board says the cycle is done (ControllerError if it failed)."""
    engine = machine.engine
    session = engine.session
    lines = session.home_lines(axes)
    # A lockout may take the homing line (grbl's `$H` in ALARM): not with a fault that
    # blocks motion (1007), whatever the lockout would say.
    async with _operation(machine, fault_first=True):
        before = engine.model.last_exception
        if session.homing_answered_at_end:
            await engine.send(lines[0], timeout=HOMING_WAIT)
            await _at_rest(machine)  # a report after the answer: out of ALARM, say
            return
        await engine.send(lines[0], timeout=ANSWER_WAIT)
        # The answer came as the cycle started; a status report asked after it shows
        # the cycle, and its end is the state leaving HOMING.
        await _fresh_report(machine)
        model = engine.model
        try:
            async with asyncio.timeout(HOMING_WAIT):
                await engine.wait_for(lambda: model.state is not MachineState.HOMING)
        except TimeoutError:
            raise ControllerTimeout(f"{machine.id}: homing did not end") from None
        failed = model.last_exception
        if failed is not before and failed is not None and session.homing_failed(failed):
            raise ControllerError(int(failed["st"]), str(failed.get("msg") or "homing failed"))
        if model.state is not None and model.state.is_lockout:
            raise ControllerError(0, f"{machine.id}: homing ended in {model.state.name}")


async def zero(machine: Machine, axes: Mapping[str, float]) -> None:
    """Set work zero: each axis named reads the value given, now, in the active WCS."""
    engine = machine.engine
    async with _operation(machine, powered=False):  # moves nothing
        line = engine.session.zero_line(engine.model.modal.get("wcs"), axes)
        await engine.send(line, timeout=ANSWER_WAIT)
        # The position reports follow the offset; ask for one now so the answer's
        # snapshot already shows it.
        await _fresh_report(machine)


async def _fresh_report(machine: Machine) -> None:
    """Ask for a full status report: answered, where the dialect has such a line."""
    line = machine.engine.session.report_line
    if line is None:
        machine.engine.query_status()
        return
    await machine.engine.send(line, timeout=ANSWER_WAIT)


def rise_to(safe_z: float | None, z_now: float | None) -> float | None:
    """The height (machine mm) to rise to before crossing: `safe_z`, unless none is known
    or the tool is already at or above it, where it crosses as it is: Z never goes
    *down* to cross (a go-to-zero, a frame; a tool change's own `max`)."""
    if safe_z is None or (z_now is not None and z_now >= safe_z):
        return None
    return safe_z


def goto_zero_lines(axes: list[str] | None, rise: float | None, *, inches: bool) -> list[str]:
    """Z up to `rise` in machine coordinates first (`rise_to`: None, no rise) whenever X
    or Y moves, asked or not; then X and Y; then Z down to its work zero, if asked: the
    tool never crosses the work low. `rise` is mm; the line is in the board's units
    (`inches`: G20), which it leaves as they are."""
    chosen = axes or ["x", "y", "z"]
    lines: list[str] = []
    flat = [a for a in chosen if a != "z"]
    if flat and rise is not None:
        height = rise / MM_PER_INCH if inches else rise
        lines.append(f"G53 G0 Z{short_number(height)}")
    if flat:
        lines.append(f"G90 G0 {axes_words(flat)}")
    if "z" in chosen:
        lines.append("G90 G0 Z0")
    return lines


async def goto_zero(machine: Machine, axes: list[str] | None) -> None:
    """Go to work zero; return once the board is at rest there."""
    engine = machine.engine
    async with _operation(machine):
        safe = machine.config.safe_z  # the board's Z travel is not read here (a query)
        # Where Z is and the board's units, as they are now: a `G20` answered a moment
        # ago shows in g2core's next report, and in grbl's `$G` after it, which
        # `_operation` waited for (`modes_known`).
        await _fresh_report(machine)
        here, _ = machine.positions_mm()
        inches = engine.model.units == "in"
        for line in goto_zero_lines(axes, rise_to(safe, here.get("z")), inches=inches):
            await engine.send(line, timeout=ANSWER_WAIT)
        # A board answers a move as it queues it, and may report rest until its
        # planner starts: at rest *at zero* is the end (or a lockout, or an error).
        chosen = axes or ["x", "y", "z"]
        position = engine.model.position
        await _at_rest(machine, lambda: all(abs(position.get(a, 0.0)) < AT_ZERO for a in chosen))


async def _at_rest(machine: Machine, there: Callable[[], bool] = lambda: True) -> None:
    """Until the board has run what it was given (rest.py's rule)."""
    await rest.at_rest(machine, there, timeout=MOVE_WAIT)


def spindle_line(state: str, speed: float | None) -> str:
    code = {"cw": "M3", "ccw": "M4", "off": "M5"}[state]
    return code if speed is None else f"{code} S{short_number(speed)}"


async def spindle(machine: Machine, state: str, speed: float | None) -> None:
    """M3/M4/M5 (with S): answered once a report read after the line says the board
    rests again, so the next operation finds the machine idle (grbl syncs the
    spindle with the planner: the line runs as a block, and the board is busy
    until it has). Off is never refused for a fault: it makes safe."""
    async with _operation(machine, powered=state != "off"):
        await machine.engine.send(spindle_line(state, speed), timeout=ANSWER_WAIT)
        await _at_rest(machine)


async def override(
    machine: Machine, feed: int | None, rapid: int | None, spindle_: int | None
) -> dict[str, float | None]:
    """Write the overrides (grbl: realtime bytes) and answer those now in force.

    The session asks the board what is in force and says when it has answered
    (`override_answers`): g2core answers the setting it stored; grbl takes its
    steps in rounds, each what one pass of its main loop takes, each checked by a
    report that follows its bytes, until `Ov:` shows the values asked, a round
    brings none nearer, or the rounds' bound is reached (well within ANSWER_WAIT).
    The answer is always the board's last word, which may differ from what was
    asked (docs/dialects.md).
    """
    engine = machine.engine
    seen = engine.session.override_answers
    engine.override(feed, rapid, spindle_)
    try:
        async with asyncio.timeout(ANSWER_WAIT):
            await engine.wait_for(lambda: engine.session.override_answers > seen)
    except TimeoutError:
        raise ControllerTimeout(f"{machine.id} did not report its overrides") from None
    return in_force(machine)


def in_force(machine: Machine) -> dict[str, float | None]:
    """The overrides the board last reported, or nulls where it never said."""
    now = machine.engine.model.overrides or {}
    return {key: now.get(key) for key in ("feed", "spindle", "rapid")}


# -- laser test-fire -----------------------------------------------------------

LASER_TEST_MAX_S: Final = 2.0  # seconds: api.md's bound on duration_s
BEAM_OFF_WAIT: Final = 5.0  # seconds past the dwell for the board to answer its M5


async def full_power(machine: Machine) -> float:
    """The S word of 100 % (grbl `$30`, g2core `th2mxs`), read from the board now."""
    key = machine.engine.session.spindle_max_setting()
    if key is None:
        raise InvalidCommand(
            Refusal.UNREADABLE,
            f"{machine.id}: its firmware has no spindle maximum to scale a laser's power by",
        )
    try:
        found = await machine.read_settings([key])
    except ControllerError as exc:
        # The build has no such setting (a g2core without a laser toolhead answers
        # `th2mxs` with 100, unrecognized name): nothing to scale the power by. Said as
        # the board's limit, before anything moves, not as a failed line.
        raise InvalidCommand(
            Refusal.UNREADABLE,
            f"{machine.id}: the board does not know {key!r}, its full-power S"
            f" ({exc.message}): its firmware has no spindle maximum to scale a laser's"
            " power by; frame at power 0 (beam off)",
        ) from None
    value = found.get(key)
    if isinstance(value, bool) or not isinstance(value, int | float) or value <= 0:
        raise ControllerError(0, f"{machine.id}: the board did not say its spindle maximum")
    return float(value)


def _check_laser(machine: Machine, power: float) -> None:
    if not machine.is_laser():
        raise InvalidCommand(
            Refusal.UNREADABLE,
            f"{machine.id} is not a laser (set laser = true in its [[machines]] table,"
            " or laser mode on the board)",
        )
    most = machine.config.laser_test_max
    if power > most:
        raise InvalidCommand(
            Refusal.BAD_NUMBER,
            f"{machine.id}: at most {most:g} % (laser_test_max in its config), not {power:g}",
        )


async def laser_test(machine: Machine, power: float, seconds: float) -> None:
    """Fire the beam standing still at `power` % for `seconds`, then always off.

    The lines (the session's `laser_test_lines`: on, dwell, off) are handed to the
    board together, so its own dwell bounds the burn and its `M5` follows even if the
    link drops or the host is gone. If the `M5` is not answered in time, or the call is
    cancelled or fails before it is, the board is reset (every firmware's reset stops
    the spindle: gnea/grbl mc_reset, g2core reboots). A feedhold during the dwell
    stops the beam too on grbl (DISABLE_LASER_DURING_HOLD, protocol.c:536).
    """
    _check_laser(machine, power)
    if not 0 < seconds <= LASER_TEST_MAX_S:
        raise InvalidCommand(Refusal.BAD_NUMBER, f"duration_s is 0 to {LASER_TEST_MAX_S:g} s")
    engine = machine.engine
    async with _operation(machine):
        engine.admit_action()  # in a lockout: its code (204/205/206), nothing sent
        speed = await full_power(machine) * power / 100.0
        for read in engine.session.laser_test_reads():
            await engine.send(read, timeout=ANSWER_WAIT)
        lines = engine.session.laser_test_lines(speed, seconds)
        wait = seconds + BEAM_OFF_WAIT
        sends = [asyncio.ensure_future(engine.send(line, timeout=wait)) for line in lines]
        off = sends[-1]
        try:
            await asyncio.gather(*(asyncio.shield(s) for s in sends))
        except BaseException:
            # Whatever went wrong before the board answered its M5: let the M5 answer
            # (it was written with the rest), and if it does not come, reset the board.
            if not await _answered(off, wait):
                log.error("laser test: beam-off not answered: resetting", machine=machine.id)
                with contextlib.suppress(Exception):
                    await machine.reset()
            raise
        finally:
            for task in sends:
                if not task.done():
                    task.cancel()
                elif not task.cancelled():
                    task.exception()  # seen: a line a kill discarded is the call's outcome


async def _answered(task: asyncio.Future[Any], wait: float) -> bool:
    """Whether the board answered this line OK within `wait` seconds."""
    done, _ = await asyncio.wait({task}, timeout=wait)
    return bool(done) and not task.cancelled() and task.exception() is None


# -- frame -----------------------------------------------------------------

FRAME_FEED: Final = 1000.0  # mm/min, when none is asked: a walk the eye can follow


def frame_lines(
    machine: Machine,
    box: Mapping[str, tuple[float, float]],
    *,
    speed: float | None,
    feed: float,
    safe_z: float | None,
    inches: bool,
    relative: bool,
) -> list[str]:
    """The job's box traced in work coordinates, at `feed`, beam off (or at S `speed`).

    Z is never moved down: a laser traces at its current Z (no Z word); a mill first
    goes up to its safe height in machine coordinates (`safe_z` None: already there).
    The board's units and distance mode are put back at the end.
    """
    (x0, x1), (y0, y1) = box["x"], box["y"]
    lines = ["M5", "G21 G90 G94"]
    if safe_z is not None:
        lines.append(f"G53 G0 Z{short_number(safe_z)}")
    lines.append(f"G0 X{short_number(x0)} Y{short_number(y0)}")
    if speed is not None:
        lines.append(machine.engine.session.beam_on_line(speed))
    f = f" F{short_number(feed)}"
    for x, y in ((x1, y0), (x1, y1), (x0, y1), (x0, y0)):
        lines.append(f"G1 X{short_number(x)} Y{short_number(y)}{f}")
        f = ""
    lines.append("M5")
    if inches:
        lines.append("G20")
    if relative:
        lines.append("G91")
    return lines


async def frame(
    machine: Machine, path: Path, power: float, feed: float | None, *, pool: WorkerPool
) -> Job:
    """Trace `path`'s XY bounding box (its analysis, work coordinates) as a make job.

    Refused (1008, as job.start) when the box leaves the travel, where the travel
    check can run (travel known, machine homed); power above 0 only on a laser, within
    `laser_test_max`; a mill needs a safe height (`safe_z`, or the Z travel's top).
    """
    if power > 0:
        _check_laser(machine, power)
    check = await analyze_for(machine, path, pool=pool)
    bounds = check.analysis.bounds
    if "x" not in bounds or "y" not in bounds:
        raise InvalidCommand(
            Refusal.UNREADABLE, f"{path.name} moves in no X and Y: no box to frame"
        )
    box = {"x": bounds["x"], "y": bounds["y"]}
    if check.frame_beyond:
        raise OutOfTravel(
            f"the frame of {path.name} leaves {machine.id}'s travel: "
            + "; ".join(check.frame_beyond),
            {"beyond_travel": check.frame_beyond},
        )
    limits = check.limits
    laser = machine.is_laser()
    homed = machine.engine.model.homed is True
    safe_z = None if laser else machine.safe_height(limits)  # unhomed: safe_z or none
    if not laser and safe_z is None:
        raise InvalidCommand(
            Refusal.UNREADABLE,
            f"{machine.id} is not a laser and its safe height is unknown: set safe_z"
            + ("" if homed else ", or home it (the Z travel's top means nothing before)"),
        )
    await modes_known(machine)  # its lines are written in the units and distance in force
    here, work = machine.positions_mm()
    z_now, z_work = here.get("z"), work.get("z")
    if safe_z is not None and "z" in bounds and z_now is not None and z_work is not None:
        # Never across lower than the program itself goes (its clearance over the work and
        # the clamps): a safe height set below it would drag the tool through them.
        top = bounds["z"][1] + z_now - z_work
        if top > safe_z:
            log.info("frame: above the safe height, at the program's top", z=top, safe_z=safe_z)
            safe_z = top
    safe_z = rise_to(safe_z, z_now)
    model = machine.engine.model
    speed = await full_power(machine) * power / 100.0 if power > 0 else None
    lines = frame_lines(
        machine,
        box,
        speed=speed,
        feed=feed or FRAME_FEED,
        safe_z=safe_z,
        inches=model.units == "in",
        relative=model.modal.get("distance") == "G91",
    )
    macros.admit_program(machine, lines, f"the frame of {path.name}")
    return await machine.start_program(lines)
