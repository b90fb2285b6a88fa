"""Resumes checked as a machinist would (issue 24): where the tool went, and the spindle.

For each shop-shaped file of tests/daemon/resume_files (`name.nc` on both dialects,
`name.<dialect>.nc` on one), on a board with stored G54/G55 offsets, through the
whole daemon and the simulated board on a pty:

1. the file runs whole; the board's record of every move it made is the reference;
2. it runs again and is lost at a line picked by a seeded random draw (unplugged:
   the board powers up with nothing of the job but its stored offsets);
3. `job.recovery` plans the resume and `job.start` runs it.

The resumed run must never take the tool lower than the file itself went at that XY
(where the file never went, lower than the file's highest point), must run every
cutting move with the spindle (speed, or laser power) the file had there, must
move a laser with the beam off until it is in position, and must end where the
whole run ended.
"""

from __future__ import annotations

import asyncio
import math
import random
import re
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio

from hostd.sim import SimController
from hostd.sim.motion import Traversed
from tests.daemon.conftest import Rpc, RpcFailure, Running, running_daemon
from tests.daemon.test_api import job_end
from tests.daemon.test_resume import _executed_at_least, _power_cycle, with_line_numbers

pytestmark = pytest.mark.asyncio

FILES = Path(__file__).parent / "resume_files"
STEP = 0.25  # mm between the points checked along a move
NEAR = 1  # cells of 1 mm around a point that count as "that XY"
SPEED = "S12000"  # what the operator sets by hand for a file whose M3 has no S
# The board's stored offsets before the first run (mm), and where the operator parks
# the machine before a job: the top of Z, then a corner of the table. On g2core the
# far corner: the resume's approach then crosses 300 mm and more (0.3 s on the x10
# board) before its spindle's dwell and plunge. Parked at the origin it crossed ~30 mm,
# 30 ms, with a 5 ms dwell: a test host late by that much under load let the board
# run out of moves there, an underflow (a job fault, as it must be: behaviour.md),
# and the resumed job failed before its first line (docs/performance.md).
SETUP = {
    "g2core": (
        ["G10 L2 P1 X20 Y20 Z40", "G10 L2 P2 X60 Y20 Z40"],
        ["G21 G53 G0 Z90", "G53 G0 X250 Y250"],  # mm: the inch file leaves the board in G20
    ),
    "grbl": (
        ["G10 L2 P1 X-40 Y-40 Z-20", "G10 L2 P2 X-80 Y-40 Z-20"],
        ["G53 G0 Z0", "G53 G0 X0 Y0"],
    ),
}
_MOVE = re.compile(r"\b(G0*[0-3])\b|[XYZ]-?[0-9.]")
_SPINDLE = re.compile(r"\bM0*(2|30|[345])\b|\bS([0-9.]+)")


def _cases() -> Iterator[object]:
    for path in sorted(FILES.glob("*.nc")):
        parts = path.name.split(".")
        for dialect in [parts[1]] if len(parts) == 3 else ["g2core", "grbl"]:
            yield pytest.param(path, dialect, id=f"{dialect}-{parts[0]}")


@pytest_asyncio.fixture
async def daemon(tmp_path: Path, request: pytest.FixtureRequest) -> AsyncIterator[Running]:
    dialect = request.node.callspec.params["dialect"]
    # The safe height in machine coordinates. The top of the Z travel would do only on a
    # homed machine (Machine.safe_height): these boards are power-cycled, never homed.
    extra: dict[str, float] = {"safe_z": 90.0 if dialect == "g2core" else 0.0}
    # The spindle's dwell is the daemon's 2 s, which also covers the host's writing the
    # plunge after it; both simulated boards divide a dwell by their speed factor (0.2 s
    # on the x10 board).
    async with running_daemon(tmp_path, dialect=dialect, **extra) as hostd:
        if dialect == "grbl":  # its `Ln:`: the job is lost at a line drawn for it
            rpc = await hostd.client()
            try:
                await hostd.idle(rpc)
                await with_line_numbers(hostd, rpc)
            finally:
                await rpc.close()
        yield hostd


@pytest.mark.parametrize(("path", "dialect"), list(_cases()))
async def test_a_lost_job_resumes_above_what_the_file_cut_with_its_spindle(
    daemon: Running, path: Path, dialect: str
) -> None:
    hostd = daemon
    rpc = await hostd.client()
    try:
        await _run(hostd, rpc, path, dialect)
    finally:
        await rpc.close()


async def _run(hostd: Running, rpc: Rpc, path: Path, dialect: str) -> None:
    sim = hostd.daemon.sims["sim1"]
    record = sim._board.traversed if isinstance(sim, SimController) else sim.board.traversed
    laser = path.stem.startswith("laser")
    by_hand = path.stem.startswith("m3_no_s")
    text = await asyncio.to_thread(path.read_text)
    await hostd.idle(rpc)
    await rpc.call("file.upload", name=path.name, data=text)
    # `status` too: each report's snapshot tells the job's executed line (_executed_at_least)
    await rpc.call("subscribe", topics=["job", "status"], machine="sim1")
    offsets, _ = SETUP[dialect]
    for line in offsets:
        await rpc.call("machine.send", machine="sim1", line=line)
    await _prepare(hostd, rpc, dialect, laser, by_hand)

    # 1. The whole run: the reference.
    record.clear()
    # `force`: the tool-change files hold M6, which job.start refuses on a machine with no
    # tool-change policy (the simulators take M6 as a no-op; what is checked is the path).
    whole = await rpc.call("job.start", machine="sim1", file=path.name, force=True)
    assert (await job_end(rpc, whole["job"]))["state"] == "completed"
    reference = list(record)
    assert reference, "the file moved nothing"

    # 2. The same job, lost at a line drawn for this file and dialect. The simulated
    # boards run ten times faster than real ones: a job that ends before the daemon
    # has lost it is run again, to be lost at an earlier line.
    for lose_at in _draw(text, f"{dialect}-{path.name}"):
        await _power_cycle(hostd, rpc)
        await _prepare(hostd, rpc, dialect, laser, by_hand)
        record.clear()
        lost = await rpc.call("job.start", machine="sim1", file=path.name, force=True)
        reached = await _executed_at_least(rpc, lost["job"], lose_at)
        if reached["state"] not in ("running", "paused"):  # it ended before it was lost
            assert reached["state"] == "completed", reached
            ended = reached
            continue
        if dialect == "grbl":  # unplugged: an Arduino powers down with its USB
            await sim.unplug()
            ended = await job_end(rpc, lost["job"])
            ran = {t.move.n for t in record}
            await sim.replug()
        else:  # g2core has power of its own: lost to a reset, which forgets the position
            await rpc.call("machine.reset", machine="sim1")
            ended = await job_end(rpc, lost["job"])
            ran = {t.move.n for t in record}
        if ended["state"] != "completed":
            break
    assert ended["state"] in ("interrupted", "failed"), ended
    await _prepare(hostd, rpc, dialect, laser, by_hand=False)

    # 3. The plan, and the resume.
    if by_hand:
        if dialect == "grbl":  # the board's S is 0 after its power-up: never S0 M3
            with pytest.raises(RpcFailure) as refused:
                await rpc.call("job.recovery", job=lost["job"])
            assert refused.value.code == 1011 and "without a speed" in refused.value.message
        await rpc.call("machine.send", machine="sim1", line=SPEED)
    plan = await rpc.call("job.recovery", job=lost["job"])
    await hostd.idle(rpc)  # the operator reads the plan: grbl answered its queries
    # Every move before the resume line was begun by the lost run (the board's record:
    # g2core's as each block starts, grbl's as each is planned): nothing is skipped.
    skipped = [t.move for t in reference if t.move.n < plan["line"] and t.move.n not in ran]
    assert not skipped, f"resumed at line {plan['line']}, past moves never made: {skipped}"
    assert not any("G10" in line for line in plan["preamble"] + plan["approach"])
    if by_hand:
        assert not any(re.search(r"\bS0\b", line) for line in plan["approach"])
    record.clear()
    resumed = await rpc.call(
        "job.start", machine="sim1", file=path.name, start_line=plan["line"], force=True
    )
    ended = await job_end(rpc, resumed["job"])
    assert ended["state"] == "completed", (ended, plan)
    after = list(record)

    where = f"{path.name} on {dialect}, resumed at line {plan['line']}: {plan['approach']}"
    low = _too_low(reference, after)
    assert low is None, f"{where}: the tool went to {low}"
    wrong = _spindle_wrong(reference, after, plan, laser, text)
    assert wrong is None, f"{where}: {wrong}"
    end, want = after[-1].move.target, reference[-1].move.target
    assert all(math.isclose(end[a], want[a], abs_tol=1e-3) for a in want), (where, end, want)


async def _prepare(hostd: Running, rpc: Rpc, dialect: str, laser: bool, by_hand: bool) -> None:
    """What the operator does after the board powers up: laser mode as the machine is
    built (a mill on grbl: $32=0), the machine parked, the spindle speed set by hand."""
    await hostd.idle(rpc)
    if dialect == "grbl" and not laser:
        await rpc.call("settings.set", machine="sim1", values={"32": 0})
        await rpc.call("settings.get", machine="sim1", keys=["32"])
    _, park = SETUP[dialect]
    for line in park + ([SPEED] if by_hand else []):
        await rpc.call("machine.send", machine="sim1", line=line)
    if dialect == "grbl":
        # grbl answers a dwell once everything before it has run (protocol_buffer_
        # synchronize): the machine is parked, not only told to park.
        await rpc.call("machine.send", machine="sim1", line="G4 P0")
    await hostd.idle(rpc)


def _draw(text: str, seed: str) -> list[int]:
    """Lines to lose the job at: one with a move drawn after the first few and before
    the last few, then earlier ones (the first move that cuts, at last)."""
    moves = [i for i, line in enumerate(text.splitlines(), 1) if _MOVE.search(line.split("(")[0])]
    drawn = random.Random(seed).choice(moves[3:-3])
    return [drawn, (drawn + moves[3]) // 2, moves[3]]


def _points(moves: list[Traversed]) -> Iterator[dict[str, float]]:
    for t in moves:
        yield from t.points(STEP)


def _too_low(reference: list[Traversed], resumed: list[Traversed]) -> str | None:
    """The first point of `resumed` below the lowest the file went near its XY, or
    below the file's highest point where the file never went; None if there is none."""
    floor: dict[tuple[int, int], float] = {}
    top = -math.inf
    for p in _points(reference):
        cell = (round(p["x"]), round(p["y"]))
        floor[cell] = min(floor.get(cell, math.inf), p["z"])
        top = max(top, p["z"])
    for p in _points(resumed):
        cx, cy = round(p["x"]), round(p["y"])
        near = [
            floor[(cx + i, cy + j)]
            for i in range(-NEAR, NEAR + 1)
            for j in range(-NEAR, NEAR + 1)
            if (cx + i, cy + j) in floor
        ]
        lowest = min(near) if near else top
        if p["z"] < lowest - 1e-3:
            return f"{p} (machine mm), where the file went no lower than Z {lowest:.3f}"
    return None


def _spindle_at(reference: list[Traversed], text: str, line: int) -> tuple[str, float] | None:
    """The spindle (and speed) the file had as `line` began: the board's, on the last
    move before it, changed by the spindle words of the lines between (an `M5`, an
    `S16000 M3` between two moves); None if no move comes before it."""
    before = [t.move for t in reference if t.move.n < line]
    if not before:
        return None
    spindle, speed = before[-1].spindle, before[-1].speed
    for code in text.splitlines()[before[-1].n : line - 1]:
        for m, s in _SPINDLE.findall(code.split("(")[0]):
            if m:
                spindle = "M5" if m in ("2", "30") else f"M{m}"  # a program end stops it
            else:
                speed = float(s)
    return spindle, speed


def _spindle_wrong(
    reference: list[Traversed],
    resumed: list[Traversed],
    plan: dict[str, Any],
    laser: bool,
    text: str,
) -> str | None:
    """The first cutting move of `resumed` whose spindle is not the file's there.

    The approach's moves are the first ones (as many as its lines with a move); the
    rest are the file's, each matched by its line number (its N word). The approach's
    plunge runs with the spindle the file had as the resume line began (`_spindle_at`);
    the first move at or after the line says so too where no move comes before it.
    """
    line = plan["line"]
    approach = sum(
        1 for entry in plan["approach"] if re.search(r"[XYZ]", entry) and "G92" not in entry
    )
    first: dict[int, Traversed] = {}
    for t in reference:
        first.setdefault(t.move.n, t)
    at_line = next((t for t in reference if t.move.n >= line), None)
    at_start = _spindle_at(reference, text, line)
    for i, t in enumerate(resumed):
        if t.move.rapid:
            if laser and t.cutting:
                return f"a rapid with the beam on: {t.move}"
            continue
        if i >= approach:
            if t.move.n not in first:
                return f"{t.move}: a move of a line the whole run never made"
            want = first[t.move.n]
        elif laser:  # the approach: in position before the beam goes on
            if t.cutting:
                return f"the beam is on before the laser is in position: {t.move}"
            continue
        elif at_start is not None:  # the approach's plunge
            got = (t.move.spindle, t.move.speed)
            if got != at_start:
                return f"{t.move} runs with {got}, the file with {at_start} at line {line}"
            continue
        elif at_line is None:
            continue  # nothing of the file moves after the line: nothing to cut
        else:
            want = at_line  # no move before the line: the first at or after it says
        got = (t.move.spindle, t.move.speed)
        if got != (want.move.spindle, want.move.speed):
            return f"{t.move} runs with {got}, the file with {want.move.spindle, want.move.speed}"
    return None
