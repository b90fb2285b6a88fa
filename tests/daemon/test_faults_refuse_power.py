"""A fault that blocks a job also blocks the operator's buttons that move or power.

Until 2026-11-29 an active, un-overridden `lid_open` (the lid of a laser open while its
main laser is selected) refused `job.start`, a frame and a jog with 1007, and let
`machine.laser_test` fire the beam, `machine.spindle` turn it on, and `machine.home`,
`machine.goto_zero` and `machine.probe` move the machine. Now each of those is 1007
with the fault's id, and nothing reaches the board. Setting work zero moves nothing and
turning the spindle off only makes safe: both are still served. An override, or the
fault's end, lets them through again.

A real daemon with a simulated g2core (sim1, the laser's safety signals wired to its
inputs) and a simulated grbl laser (sim2) on real ptys, through the real socket.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.daemon.conftest import G2, GRBL, Rpc, Running
from tests.daemon.test_api import fails
from tests.daemon.test_faults import SIGNALS, fault_became
from tests.daemon.test_operation_gates import _daemon, g2_sim, grbl_alarm_after_a_hard_limit
from tests.daemon.test_operations import lines_sent
from tests.daemon.test_power import grbl_board, grbl_sim

pytestmark = pytest.mark.asyncio

# Each request that moves the machine or powers its spindle or beam, on g2core.
POWERED = [
    ("machine.home", {}),
    ("machine.goto_zero", {}),
    ("machine.spindle", {"state": "cw", "speed": 1000}),
    ("machine.spindle", {"state": "ccw", "speed": 1000}),
    ("machine.probe", {"kind": "z", "plate": 10, "confirmed": True}),
]
# What any of them would have written first: a homing, a move, the spindle on, a probe.
MOVING = (b"G28.2", b"G0", b"G1", b"M3", b"M4", b"G38")


async def _lid_open(hostd: Running, rpc: Rpc) -> None:
    """The lid open on the laser, and nothing else wrong (its coolant flowing)."""
    sim = g2_sim(hostd)
    await rpc.call("subscribe", topics=["fault"], machine=G2)
    sim.set_analog(1, 3.0)  # coolant flowing: an unpowered flow meter reads 0
    faults = await rpc.call("fault.list", machine=G2)
    if any(f["id"] == "water_flow" and f["active"] for f in faults):
        await fault_became(rpc, "water_flow", False)
    sim.set_input(2, 1)  # the main laser selected
    sim.set_input(1, 1)  # the lid open
    await fault_became(rpc, "lid_open", True)


def _moving(written: list[bytes]) -> list[bytes]:
    return [line for line in written if line.lstrip(b"N0123456789 ").startswith(MOVING)]


async def test_a_blocking_fault_refuses_every_request_that_moves_or_powers(
    tmp_path: Path,
) -> None:
    async with _daemon(tmp_path, g2={"signals": SIGNALS}) as (hostd, rpc):
        await _lid_open(hostd, rpc)
        before = len(lines_sent(hostd, G2))
        where = g2_sim(hostd).position
        for method, params in POWERED:
            err = await fails(1007, rpc.call(method, machine=G2, **params))
            assert err.data == ["lid_open"], (method, err)
            assert "lid_open" in err.message, (method, err.message)
        assert _moving(lines_sent(hostd, G2)[before:]) == []
        assert g2_sim(hostd).position == where
        # What moves nothing, or only makes safe, is served.
        await rpc.call("machine.zero", machine=G2, axes={"x": 0})
        await rpc.call("machine.spindle", machine=G2, state="off")
        # Overridden, the operator takes the risk: the same requests run.
        await rpc.call("fault.override", machine=G2, fault="lid_open", override=True)
        await rpc.call("machine.spindle", machine=G2, state="cw", speed=1000)
        await rpc.call("machine.spindle", machine=G2, state="off")
        await rpc.call("machine.home", machine=G2)
        assert (await rpc.call("machine.status", machine=G2))["homed"] is True


async def test_a_laser_test_fire_is_refused_while_a_fault_blocks_and_fires_after(
    tmp_path: Path,
) -> None:
    async with _daemon(tmp_path, grbl={"laser": True}) as (hostd, rpc):
        await rpc.call("subscribe", topics=["fault"], machine=GRBL)
        grbl_sim(hostd).inject_garbage(b"\xff\xfe\x01 noise\n")  # line noise: `serial`
        await fault_became(rpc, "serial", True)
        board = grbl_board(hostd)
        err = await fails(
            1007, rpc.call("machine.laser_test", machine=GRBL, power=5, duration_s=0.3)
        )
        assert err.data == ["serial"], err
        assert [p for _, p in board.beam if p > 0] == []
        assert b"M3" not in b"".join(lines_sent(hostd, GRBL))
        await rpc.call("fault.clear", machine=GRBL, fault="serial")
        assert await rpc.call("machine.laser_test", machine=GRBL, power=5, duration_s=0.3) == {}
        assert any(p > 0 for _, p in board.beam) and board.beam_power() == 0.0


async def test_homing_out_of_a_grbl_alarm_is_refused_while_a_fault_blocks(
    tmp_path: Path,
) -> None:
    """grbl takes `$H` in ALARM (its way out where it homes): a blocking fault refuses it
    all the same (1007), and the spindle turned on in the same ALARM is the lockout's
    code first (204), as every request the lockout itself refuses."""
    async with _daemon(tmp_path) as (hostd, rpc):
        await rpc.call("subscribe", topics=["fault"], machine=GRBL)
        sim = await grbl_alarm_after_a_hard_limit(hostd, rpc)
        sim.inject_garbage(b"\xff\xfe\x01 noise\n")
        await fault_became(rpc, "serial", True)
        before = len(lines_sent(hostd, GRBL))
        err = await fails(1007, rpc.call("machine.home", machine=GRBL))
        assert err.data == ["serial"], err
        assert b"$H" not in lines_sent(hostd, GRBL)[before:]
        await fails(204, rpc.call("machine.spindle", machine=GRBL, state="cw", speed=100))
        await rpc.call("fault.clear", machine=GRBL, fault="serial")
        await rpc.call("machine.home", machine=GRBL)
        snapshot = await rpc.call("machine.status", machine=GRBL)
        assert snapshot["state"]["name"] == "READY" and snapshot["homed"] is True


async def test_the_console_refuses_a_line_that_moves_or_powers_while_a_fault_blocks(
    tmp_path: Path,
) -> None:
    """`machine.send` is the console: a line that moves the machine or starts its spindle
    or beam is 1007 as a jog is, G-code as text or in g2core's JSON `gc`; what moves
    nothing, or only makes safe, still goes."""
    async with _daemon(tmp_path, g2={"signals": SIGNALS}) as (hostd, rpc):
        await _lid_open(hostd, rpc)
        before = len(lines_sent(hostd, G2))
        for line in ("G1 X10 F100", "X5", '{"gc":"M3 S500"}', "G28.2 X0"):
            err = await fails(1007, rpc.call("machine.send", machine=G2, line=line))
            assert err.data == ["lid_open"] and "the line" in err.message, (line, err.message)
        assert _moving(lines_sent(hostd, G2)[before:]) == []
        for line in ("M5", "G90", "{sr:n}", "G10 L20 P1 X0", "M8", "M9"):
            await rpc.call("machine.send", machine=G2, line=line)
        await rpc.call("fault.override", machine=G2, fault="lid_open", override=True)
        await rpc.call("machine.send", machine=G2, line="G0 X1")


async def test_grbl_jogs_homing_and_a_moving_startup_block_are_refused_while_a_fault_blocks(
    tmp_path: Path,
) -> None:
    async with _daemon(tmp_path, grbl={"maintenance": True}) as (hostd, rpc):
        await rpc.call("subscribe", topics=["fault"], machine=GRBL)
        grbl_sim(hostd).inject_garbage(b"\xff\xfe\x01 noise\n")
        await fault_became(rpc, "serial", True)
        before = len(lines_sent(hostd, GRBL))
        for line in ("$J=G91 X1 F100", "$H", "G0 X1"):
            await fails(1007, rpc.call("machine.send", machine=GRBL, line=line))
        # grbl runs a startup block once as it stores it: one that moves is refused.
        err = await fails(1007, rpc.call("machine.maintenance", machine=GRBL, line="$N0=G0 X5"))
        assert "moves the machine" in err.message, err.message
        written = lines_sent(hostd, GRBL)[before:]
        assert not [ln for ln in written if ln.startswith((b"$J", b"$H", b"G0", b"$N0"))]
        await rpc.call("machine.send", machine=GRBL, line="$G")  # a query goes
