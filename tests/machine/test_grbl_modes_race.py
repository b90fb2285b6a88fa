"""grbl's modes after a client's line: nothing judged in units the board has left.

grbl reports its units and distance mode only in `$G`'s answer, which the
session asks after each client's G-code line. The machine is idle while
that `$G` is out (a query keeps it quiet), so a jog or an operation asked
right after a `G20` could read the old units: a jog bound by the travel in
millimetres would pass 20 inches. `operations.modes_known` waits for the
answer first (the API's jog and send, every operation, the frame).
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from hostd.machine import operations
from hostd.machine.guard import MaintenanceRefused, check_jog
from tests.machine.test_grbl import GRBL, GrblBench, grbl_bench

pytestmark = pytest.mark.asyncio


async def g20_with_its_modes_poll_held(bench: GrblBench) -> None:
    """`G20` answered, and the session's `$G` after it written but not yet read."""
    engine = bench.machine.engine
    sim = bench.board
    sim.queue_input(True)
    sent = asyncio.ensure_future(engine.send("G20"))
    # Let go once the whole line waits in the board's input: hostd's write is not the
    # board's read, and a line split across the release would be held again, unanswered.
    await sim.wait_for(lambda: b"G20\n" in bytes(sim.board.queued or b""))
    sim.queue_input(False)  # the board reads `G20` and answers it...
    sim.queue_input(True)  # ...and holds what comes next: the session's `$G`
    assert (await sent).ok
    assert engine.session.modes_pending()
    assert engine.model.units == "mm"  # what the model knew before


async def test_a_jog_asked_right_after_g20_is_bounded_in_inches(tmp_path: Path) -> None:
    async with grbl_bench(tmp_path, GRBL) as bench:
        machine = bench.machine

        async def jog_asked() -> None:  # as machine.jog's API method checks it
            await operations.modes_known(machine)
            check_jog(machine, {"x": 20.0})  # 20 in is 508 mm: past the 200 mm travel

        await g20_with_its_modes_poll_held(bench)
        jog = asyncio.ensure_future(jog_asked())
        await asyncio.sleep(0)
        assert not jog.done()  # waiting for `$G`, not judged in millimetres
        bench.board.queue_input(False)
        with pytest.raises(MaintenanceRefused, match="more than the axis travels"):
            await jog
        assert machine.engine.model.units == "in"


async def test_a_go_to_zero_right_after_g20_lifts_in_inches(tmp_path: Path) -> None:
    """Its lift to `safe_z` (5 mm) is written in the board's units: `G53 G0 Z5` read in
    G20 is 127 mm up. (Its fresh report, a `?` sent as a line, is answered after the
    held `$G` too: this guards the whole, where the jog above shows the wait itself.)"""
    async with grbl_bench(tmp_path, GRBL, safe_z=5.0) as bench:
        await g20_with_its_modes_poll_held(bench)
        going = asyncio.ensure_future(operations.goto_zero(bench.machine, ["x", "y"]))
        await asyncio.sleep(0)
        assert not going.done()
        bench.board.queue_input(False)
        await going
        lifts = [t for t in bench.recorder.tx() if t.startswith("G53 G0 Z")]
        assert lifts == ["G53 G0 Z0.1969"], lifts  # 5 mm in inches, not 5 in
        assert not bench.machine.engine.session.modes_pending()
