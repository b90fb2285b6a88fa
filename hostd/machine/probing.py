"""Probing with a touch plate (issue 29): Z, or an XYZ corner, then work zero from it.

The sequence, each step one line sent as any client line is sent (`Engine.send`,
so the session's command-class admission judges it), waiting for each answer:

1. Admission as for every operation of operations.py: connected, idle, one at a
   time; in a lockout the command class answers (204/205/206) before anything.
2. The probe input must be seen working: it reads closed (the operator touches
   the plate to the bit) and then open again, within `wait` seconds. Where the
   board cannot show its input the operator's `confirmed` stands in for it.
   A short pause follows, for their hands to leave the plate.
3. `G21 G90`, then `G38.2 Z<max_travel below> F<feed>` (absolute targets, from the
   position the board reports at rest before each move). The board's probe report
   (`{prb:..}`, `[PRB:..]`) says where it touched, in machine coordinates; the
   work position is then set with the session's `G10 L20` so that the touch
   point reads the plate's thickness (plus how far the board coasted past it).
   Then the bit goes up `retract`.
4. For "xyz", the same for X, then Y: off the plate by half the travel, down
   beside it with G38.3 (which stops, without an alarm, should it meet the
   plate: the bit started too far in), into the wall with G38.2, zeroed for the
   wall, the plate's thickness and the bit's radius, back out and up, and over
   the plate again (`G53 G0` to where it started).
5. G20 or G91 back, if either was in force.

A probe that does not touch is the board's alarm (G38.2: g2core er 250, grbl
ALARM:5): it stops where its travel ended. Nothing more is sent; the error
says what happened, where the bit is and that the alarm must be cleared.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncGenerator
from typing import Any, Final, Literal

import structlog

from hostd.machine.events import Event, StatusChanged
from hostd.machine.machine import Machine
from hostd.machine.operations import _fresh_report, _operation
from hostd.machine.rest import at_rest
from hostd.machine.supervisor import State as SupState
from hostd.protocol.commands import InvalidCommand, Refusal
from hostd.protocol.errors import Busy, ControllerError, ControllerTimeout, MachineError
from hostd.protocol.probing import CLEARANCE, ProbeInput, number, probe_line, touch_value

log = structlog.get_logger(__name__)

ANSWER_WAIT: Final = 10.0
REST_WAIT: Final = 60.0
POLL: Final = 0.1  # s between reads of the probe input while waiting for the touch
SETTLE: Final = 1.0  # s after the touch before anything moves: hands off the plate
MAX_WAIT: Final = 120.0  # s the touch may be waited for at most
REPORT_AFTER_REFUSAL: Final = 2.0  # s for a probe report after the line itself failed


class ProbeRefused(MachineError):
    """The probe cannot start as things are (1003): its input was not seen working."""

    code = 1003


async def probe(
    machine: Machine,
    kind: Literal["z", "xyz"],
    plate: float,
    *,
    feed: float,
    max_travel: float,
    retract: float,
    tool_diameter: float = 0.0,
    confirmed: bool = False,
    wait: float = 30.0,
) -> dict[str, Any]:
    """Probe and set work zero; `{"position": {axis: machine mm of each touch}, "zeroed"}`."""
    engine = machine.engine
    session = engine.session
    model = engine.model
    plog = log.bind(machine=machine.id, kind=kind)
    async with _operation(machine):
        engine.admit_action()  # a lockout: its code, before the input is even read
        bodies = [
            (await engine.send(q, timeout=ANSWER_WAIT)).body for q in session.probe_input_reads()
        ]
        how = session.probe_input(bodies)
        await _seen_working(machine, how, min(wait, MAX_WAIT), confirmed)
        await asyncio.sleep(SETTLE)
        if machine.supervisor.state is not SupState.IDLE or session.locked():
            raise Busy(f"{machine.id} is busy now: nothing was moved")
        await _at_rest(machine)  # a fresh report: the modes and where the tool is now
        units, distance = model.units, model.modal.get("distance")
        start = machine.positions_mm()[0]  # mm, as the G53 moves back are written (G21)
        position: dict[str, float] = {}
        zeroed: list[str] = []
        # Absolute targets, from the work position the board reports at rest before
        # each move: a G91 left in force by a probe that ends in an alarm (nothing
        # can be sent then to undo it) would turn the next G0 X0 into a move by 0.
        await _send(machine, "G21 G90")
        # Z: onto the plate's top.
        position["z"] = await _touch(machine, "z", -max_travel, feed)
        await _zero(machine, "z", touch_value("z", plate, tool_diameter), position["z"])
        zeroed.append("z")
        await _move(machine, "z", retract)
        if kind == "xyz":
            for axis in ("x", "y"):
                position[axis] = await _wall(machine, axis, plate, feed, max_travel, retract)
                await _zero(machine, axis, touch_value(axis, plate, tool_diameter), position[axis])
                zeroed.append(axis)
                await _move(machine, axis, -retract)
                await _move(machine, "z", retract + plate / 2)
                if axis in start:  # G53: machine coordinates
                    await _send(machine, f"G53 G0 {axis.upper()}{number(start[axis])}")
        restore = ("G20" if units == "in" else "") + (" G91" if distance == "G91" else "")
        if restore:
            await _send(machine, restore.strip())
        await _at_rest(machine)
        plog.info("probed", position=position, zeroed=zeroed)
        return {"position": position, "zeroed": zeroed}


async def _seen_working(machine: Machine, how: ProbeInput, wait: float, confirmed: bool) -> None:
    """The input reads closed, then open, within `wait` s; or the operator confirmed."""
    if how.key is None:
        if confirmed:
            return
        raise InvalidCommand(Refusal.UNREADABLE, _cannot_show(machine))
    closed = False
    try:
        async with (
            asyncio.timeout(wait),
            contextlib.aclosing(_input_states(machine, how)) as states,
        ):
            async for state in states:
                if state is None:
                    if confirmed:
                        return
                    raise InvalidCommand(Refusal.UNREADABLE, _cannot_show(machine))
                if state:
                    closed = True
                elif closed:
                    return
    except TimeoutError:
        pass
    if closed:
        raise ProbeRefused(
            f"{machine.id}: the probe input closed but never opened again within {wait:g} s:"
            " take the plate off the bit (is the clip touching the plate?); nothing was moved"
        )
    raise ProbeRefused(
        f"{machine.id}: the probe input was not seen working: it never closed within {wait:g} s."
        " Touch the plate to the bit to show it works (check the clip and the wiring);"
        " nothing was moved"
    )


def _cannot_show(machine: Machine) -> str:
    return (
        f"{machine.id} does not show its probe input: touch the plate to the bit to check it"
        " yourself, then probe with confirmed: true"
    )


async def _input_states(machine: Machine, how: ProbeInput) -> AsyncGenerator[bool | None, None]:
    """Each reading of the probe input, in order, from now on."""
    engine = machine.engine
    key = how.key
    assert key is not None
    if how.query is not None:
        while True:
            value = (await engine.send(how.query, timeout=ANSWER_WAIT)).body.get(key)
            yield None if value is None else bool(value)
            await asyncio.sleep(POLL)
    seen: list[Any] = []

    def on_event(event: Event) -> None:
        if isinstance(event, StatusChanged) and key in event.report:
            seen.append(event.report[key])

    unsubscribe = machine.hub.subscribe(on_event)
    try:
        while True:
            if not seen:
                engine.query_status()
                await engine.wait_for(lambda: bool(seen))
            yield bool(seen.pop(0))
            if not seen:
                await asyncio.sleep(POLL)
    finally:
        unsubscribe()


async def _send(machine: Machine, line: str) -> None:
    await machine.engine.send(line, timeout=ANSWER_WAIT)


async def _target(machine: Machine, axis: str, delta: float) -> float:
    """The work position `delta` from where the tool rests now (mm: G21 is in force)."""
    await _at_rest(machine)
    now = machine.positions_mm()[1].get(axis)  # mm, as the moves are written (G21)
    if now is None:
        raise ControllerError(0, f"{machine.id} did not report its {axis.upper()} position")
    return now + delta


async def _move(machine: Machine, axis: str, delta: float) -> None:
    target = await _target(machine, axis, delta)
    await _send(machine, f"G0 {axis.upper()}{number(target)}")


async def _touch(machine: Machine, axis: str, distance: float, feed: float) -> float:
    """A G38.2 move; the machine position where it touched, once the board is at rest.

    ControllerError naming what happened when it did not touch (the board is in
    ALARM then, where its travel ended, and nothing more is sent).
    """
    line = probe_line(axis, await _target(machine, axis, distance), feed)
    report = await _probe_move(machine, line, abs(distance), feed)
    where = report["position"].get(axis)
    if not report["ok"] or where is None:
        raise await _missed(machine, axis, distance)
    await _at_rest(machine)
    # In the units the board reports its machine position in (grbl's PRB follows $13
    # as MPos does, report.c; g2core's prb is mm): mm here.
    return float(where) * machine.engine.session.position_scales()[0]


async def _wall(
    machine: Machine, axis: str, plate: float, feed: float, max_travel: float, retract: float
) -> float:
    """Off the plate, down beside it, into its wall: where the bit's side met it."""
    a = axis.upper()
    await _move(machine, axis, -max_travel * CLEARANCE)
    down = retract + plate / 2
    line = probe_line("z", await _target(machine, "z", -down), feed, must_touch=False)
    report = await _probe_move(machine, line, down, feed)
    if report["ok"]:
        raise ProbeRefused(
            f"{machine.id}: the bit met the plate going down beside it, {max_travel * CLEARANCE:g}"
            f" mm off in {a}: start it over the plate nearer the corner (within"
            f" {max_travel * CLEARANCE:g} mm of each wall, less its radius); it stopped there"
        )
    await _at_rest(machine)
    return await _touch(machine, axis, max_travel, feed)


async def _probe_move(machine: Machine, line: str, travel: float, feed: float) -> dict[str, Any]:
    """Send a G38 line; the probe report it ends with (the snapshot's `probe`)."""
    engine = machine.engine
    model = engine.model
    before = model.probe
    bound = ANSWER_WAIT + travel / feed * 60.0 * 2
    deadline = time.monotonic() + bound
    try:
        await engine.send(line, timeout=bound)
    except MachineError as exc:
        # grbl may print the alarm before the report; a line refused outright has none.
        try:
            async with asyncio.timeout(REPORT_AFTER_REFUSAL):
                await engine.wait_for(lambda: model.probe is not before)
        except TimeoutError:
            raise exc from None
    try:
        async with asyncio.timeout(max(deadline - time.monotonic(), ANSWER_WAIT)):
            await engine.wait_for(lambda: model.probe is not before)
    except TimeoutError:
        raise ControllerTimeout(f"{machine.id}: no probe report after {line!r}") from None
    assert model.probe is not None
    return model.probe


async def _missed(machine: Machine, axis: str, distance: float) -> MachineError:
    """What a probe that did not touch tells the operator: where the board stopped, read
    from a status report asked now. Not from the probe report: grbl's `[PRB:]` after a
    miss still holds the last touch (gnea motion_control.c:296-298 copies the position
    only on a touch or with G38.3/.5), where g2core's `prb` is where it stopped
    (cycle_probing.cpp:117, :424)."""
    model = machine.engine.model
    with contextlib.suppress(MachineError):  # unanswered: the last report it gave, then
        await _fresh_report(machine)
    stopped = ", ".join(
        f"{a.upper()}{v:.3f}" for a, v in machine.positions_mm()[0].items() if a in "xyz"
    )
    state = model.state.name if model.state is not None else "an unknown state"
    exc = model.last_exception or {}
    status = exc.get("st") if isinstance(exc.get("st"), int) else 0
    return ControllerError(
        int(status or 0),
        f"the {axis.upper()} probe did not touch within {abs(distance):g} mm: the board stopped"
        f" at {stopped} (machine, mm) and is in {state}; nothing more was sent. Check the plate"
        " is under the bit and its clip is on, then clear the alarm",
    )


async def _zero(machine: Machine, axis: str, value: float, touched: float) -> None:
    """`axis` reads `value` at the touch point: at the touch point plus how far the
    board went on past it (grbl decelerates past the trip; g2core backs off to it)."""
    engine = machine.engine
    now = machine.positions_mm()[0].get(axis)
    reading = value + (now - touched if now is not None else 0.0)
    await _send(machine, engine.session.work_zero_line({axis: reading}))


async def _at_rest(machine: Machine) -> None:
    """Until a report asked for now says the board rests with nothing of ours queued
    (rest.py's rule), asked again every POLL while it does not: a report taken as a
    move starts says it runs, and the board's own next report may be a status
    interval away."""
    await at_rest(machine, timeout=REST_WAIT, what="the probe's move", poll=POLL)
