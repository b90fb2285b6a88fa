"""A fault that blocks a job, become active while an operation moves the machine or powers
its beam, stops that operation as it stops a job.

Until 2026-11-29 a lid opened or the coolant stopping during a laser's test-fire left the
beam on for the rest of its dwell, and a go-to-zero ran on to zero: only a job (and a
jog, a job row) was stopped. Now the board gets the dialect's job kill at once and the
operation ends with the fault's 1007 (hostd/machine/machine_core.py,
`_stop_powered_operation`). Each test fails on the old code: the operation ends as if
nothing happened.

A real `Machine` on a simulated board over a pty, at the board's real speed (a test-fire's
dwell and a go-to-zero's rapid take their real time), with the safety signals wired to
its inputs.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from hostd.machine import operations, rest
from hostd.machine.supervisor import State as Sup
from hostd.protocol.errors import FaultActive
from hostd.protocol.states import MachineState
from hostd.sim.config import SimConfig
from hostd.sim.grbl.config import GrblConfig
from tests.machine.conftest import bench_for
from tests.machine.test_grbl import grbl_bench

pytestmark = pytest.mark.asyncio

# grbl's probe pin (`Pn:P`) as a coolant flow switch: a signal any grbl build reports.
FLOW_SWITCH = {"coolant_flow_low": {"key": "pin_p", "equals": 1}}
LASER = GrblConfig(flavour="grbl", speed_factor=1.0, feedhold_decel=0.02, laser_mode=True)
LID = {"lid_open": {"key": "in1", "equals": 1}, "main_laser": {"key": "in2", "equals": 1}}


async def test_the_coolant_stopping_during_a_test_fire_ends_the_beam_with_1007(
    tmp_path: Path,
) -> None:
    async with grbl_bench(tmp_path, LASER, signals=FLOW_SWITCH, laser=True) as bench:
        sim, machine = bench.board, bench.machine
        board = sim.board
        firing = asyncio.create_task(operations.laser_test(machine, 5, 2.0))
        await sim.wait_for(lambda: board.beam_power() > 0)
        before = len(sim.received)
        sim.probe(True)  # the flow switch opens: water_flow, a hardware fault
        with pytest.raises(FaultActive) as stopped:
            await firing
        assert stopped.value.data == ["water_flow"]
        assert board.beam_power() == 0.0
        written = b"".join(r.data for r in list(sim.received)[before:])
        assert b"!" in written, written  # the job kill: a feedhold first, the beam off
        assert machine.operation_fault is None and machine.powered_operation is None
        # Refused while it lasts; once the flow is back, the next test-fire runs.
        with pytest.raises(FaultActive):
            await operations.laser_test(machine, 5, 0.2)
        sim.probe(False)
        await machine.engine.wait_for(lambda: not machine.faults.blocking())
        await bench.supervisor(Sup.IDLE)
        await operations.laser_test(machine, 5, 0.2)
        assert board.beam_power() == 0.0


async def test_a_lid_opened_during_a_go_to_zero_stops_the_machine_short_of_zero(
    tmp_path: Path,
) -> None:
    async with bench_for(tmp_path, sim_config=SimConfig(speed_factor=1.0), signals=LID) as bench:
        machine, sim = bench.machine, bench.sim
        sim.set_input(2, 1)  # the main laser selected, the lid closed
        await machine.send("G90 G0 X150")
        position = machine.engine.model.position
        await rest.at_rest(machine, lambda: abs(position.get("x", 0.0) - 150) < 0.01, timeout=30)
        going = asyncio.create_task(operations.goto_zero(machine, ["x"]))
        await sim.wait_for(lambda: sim.position["x"] < 140, timeout=10)
        sim.set_input(1, 1)  # the lid opens mid-move
        with pytest.raises(FaultActive) as stopped:
            await going
        assert stopped.value.data == ["lid_open"]
        await sim.wait_for(lambda: sim.state is not MachineState.RUN, timeout=10)
        assert sim.position["x"] > 1.0, sim.position  # stopped where it was, not at zero
