"""Probing with a touch plate (issue 29) on both dialects, through the real socket.

A simulated g2core (sim1) and grbl (sim2) on real ptys, each with a touch plate
on its work (hostd/sim/probing.py TouchPlate, wired to the probe input as each
firmware reads it). What a user would notice: after a Z probe the work Z reads
the plate's thickness at the touch; after a corner probe X and Y read the work's
corner; a probe is refused until the input was seen working; a probe that finds
nothing fails saying so and the machine stays where the board stopped it.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio

from hostd.machine import probing
from hostd.sim import SimController
from hostd.sim.grbl.controller import GrblSimController
from hostd.sim.probing import TouchPlate
from tests.daemon.conftest import Rpc, Running, running_daemon
from tests.daemon.test_api import fails, job_end

pytestmark = pytest.mark.asyncio

G2, GRBL = "sim1", "sim2"
MACHINES = (G2, GRBL)
PLATE = 10.0  # mm thick
TOP = -3.0  # machine Z of the plate's top, 3 mm under the bit where the sims start
FAST = {"feed": 600.0, "max_travel": 10.0, "retract": 2.0}


@pytest_asyncio.fixture
async def both(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> AsyncIterator[tuple[Running, Rpc]]:
    # The pause for the operator's hands is a constant of a second; the tests have none.
    monkeypatch.setattr(probing, "SETTLE", 0.0)
    # grbl polls `?` once a second here, so the operator's touch (two reports long) is
    # seen by the probe's own reads, not used up by polls before it starts.
    per_machine = [{}, {"dialect": "grbl", "status_interval": 1.0}]
    async with running_daemon(tmp_path, machines=2, per_machine=per_machine) as d:
        client = await d.client()
        await client.call("subscribe", topics=["job"])
        for machine in MACHINES:
            await d.idle(client, machine)
        yield d, client
        await client.close()


def sim_of(hostd: Running, machine: str) -> SimController | GrblSimController:
    return hostd.daemon.sims[machine]


def lines_sent(hostd: Running, machine: str) -> list[bytes]:
    sim = sim_of(hostd, machine)
    if isinstance(sim, GrblSimController):
        realtime = b"?!~\x18" + bytes(range(0x80, 0x100))
        data = b"".join(r.data for r in sim.received).translate(None, realtime)
        return [line.strip() for line in data.split(b"\n") if line.strip()]
    return [r.data.strip() for r in sim.received if r.kind == "line"]


def moves_sent(hostd: Running, machine: str) -> list[bytes]:
    return [line for line in lines_sent(hostd, machine) if line.startswith((b"G0", b"G38", b"G1"))]


def touch(hostd: Running, machine: str) -> None:
    """The operator touches the plate to the bit, then lets go."""
    sim_of(hostd, machine).touch(reads=2)


@pytest.mark.parametrize("machine", MACHINES)
async def test_a_z_probe_sets_work_z_to_the_plate_thickness_at_the_touch(
    both: tuple[Running, Rpc], machine: str
) -> None:
    hostd, rpc = both
    sim_of(hostd, machine).touch_plate(TouchPlate(top=TOP))
    touch(hostd, machine)
    result = await rpc.call("machine.probe", machine=machine, kind="z", plate=PLATE, **FAST)
    assert result["zeroed"] == ["z"]
    assert result["position"]["z"] == pytest.approx(TOP)
    snap = await rpc.call("machine.status", machine=machine)
    # Retracted 2 mm above the plate's top, which is the plate's thickness above the work.
    assert snap["machine_position"]["z"] == pytest.approx(TOP + 2.0, abs=0.001)
    assert snap["work_position"]["z"] == pytest.approx(PLATE + 2.0, abs=0.001)
    assert snap["probe"]["ok"] is True
    assert b"G38.2 Z-10 F600" in lines_sent(hostd, machine)
    # Absolute moves only: no G91 is ever left in force (a job's G0 X0 goes to zero).
    assert b"G21 G90" in lines_sent(hostd, machine)
    assert not any(b"G91" in line for line in lines_sent(hostd, machine))


async def test_a_grbl_reporting_inches_is_probed_in_mm_all_the_same(
    both: tuple[Running, Rpc],
) -> None:
    """`$13=1`: grbl reports its positions and probe result in inches, whatever G21 says
    (report.c). The probe's moves are written in mm: read as mm, those inches put the
    retract, the zero and the moves back 25.4 times too near."""
    hostd, rpc = both
    await rpc.call("settings.set", machine=GRBL, values={"13": 1})
    await hostd.idle(rpc, GRBL)
    sim_of(hostd, GRBL).touch_plate(TouchPlate(top=TOP))
    touch(hostd, GRBL)
    result = await rpc.call("machine.probe", machine=GRBL, kind="z", plate=PLATE, **FAST)
    # mm, as documented, to the 0.0001 in the board reports in
    assert result["position"]["z"] == pytest.approx(TOP, abs=0.003)
    snap = await rpc.call("machine.status", machine=GRBL)
    assert snap["position_units"] == {"machine": "in", "work": "in"}
    assert snap["machine_position"]["z"] == pytest.approx((TOP + 2.0) / 25.4, abs=1e-4)
    assert snap["work_position"]["z"] == pytest.approx((PLATE + 2.0) / 25.4, abs=1e-4)


async def test_a_miss_on_a_grbl_reporting_inches_says_where_it_stopped_in_mm(
    both: tuple[Running, Rpc],
) -> None:
    hostd, rpc = both
    await rpc.call("settings.set", machine=GRBL, values={"13": 1})
    await hostd.idle(rpc, GRBL)
    touch(hostd, GRBL)  # works when touched, but no plate is under the bit
    err = await fails(1005, rpc.call("machine.probe", machine=GRBL, kind="z", plate=PLATE, **FAST))
    # The board said Z-0.3937 (inches): the operator reads the mm the probe was asked in.
    assert "the board stopped at X0.000, Y0.000, Z-10.000 (machine, mm)" in err.message


async def test_a_board_in_g91_is_back_in_g91_after_the_probe(both: tuple[Running, Rpc]) -> None:
    hostd, rpc = both
    sim_of(hostd, G2).touch_plate(TouchPlate(top=TOP))
    await rpc.call("machine.send", machine=G2, line="G91")
    touch(hostd, G2)
    await rpc.call("machine.probe", machine=G2, kind="z", plate=PLATE, **FAST)
    assert [line for line in lines_sent(hostd, G2) if line[:1] == b"G"][-1] == b"G91"
    snap = await rpc.call("machine.status", machine=G2)
    assert snap["distance"] == "G91"
    assert snap["work_position"]["z"] == pytest.approx(PLATE + 2.0, abs=0.001)


@pytest.mark.parametrize("machine", MACHINES)
async def test_a_corner_probe_zeroes_the_work_corner_for_the_plate_and_the_bit(
    both: tuple[Running, Rpc], machine: str
) -> None:
    hostd, rpc = both
    # The plate's walls: the bit starts over the plate, 2.5 mm in from each wall's face
    # (its side 1 mm in): within half the travel of it, as docs/operations.md asks.
    plate = TouchPlate(top=TOP, x_face=-2.5, y_face=-2.5, tool_radius=1.5)
    sim_of(hostd, machine).touch_plate(plate)
    touch(hostd, machine)
    result = await rpc.call(
        "machine.probe", machine=machine, kind="xyz", plate=PLATE, tool_diameter=3.0, **FAST
    )
    assert result["zeroed"] == ["z", "x", "y"]
    assert result["position"]["x"] == pytest.approx(-4.0)  # the wall less the bit's radius
    assert result["position"]["y"] == pytest.approx(-4.0)
    snap = await rpc.call("machine.status", machine=machine)
    # Back over the plate where it started (machine 0); the work's edges are behind the
    # walls, a plate's thickness on from their faces: X0 and Y0 at machine 7.5.
    assert_zeroed_over_the_plate(snap)


@pytest.mark.parametrize("machine", MACHINES)
async def test_a_probe_is_refused_when_the_input_was_never_seen_working(
    both: tuple[Running, Rpc], machine: str
) -> None:
    hostd, rpc = both
    sim_of(hostd, machine).touch_plate(TouchPlate(top=TOP))
    err = await fails(
        1003, rpc.call("machine.probe", machine=machine, kind="z", plate=PLATE, wait=0.5, **FAST)
    )
    assert "not seen working" in err.message
    assert moves_sent(hostd, machine) == []


@pytest.mark.parametrize("machine", MACHINES)
async def test_a_probe_input_that_stays_closed_is_refused(
    both: tuple[Running, Rpc], machine: str
) -> None:
    hostd, rpc = both
    sim = sim_of(hostd, machine)
    if isinstance(sim, GrblSimController):
        sim.probe(True)  # the clip on the plate, or a shorted wire
    else:
        sim.set_input(5, 1)  # prbin's input
    err = await fails(
        1003, rpc.call("machine.probe", machine=machine, kind="z", plate=PLATE, wait=0.5, **FAST)
    )
    assert "never opened again" in err.message
    assert moves_sent(hostd, machine) == []


@pytest.mark.parametrize("machine", MACHINES)
async def test_a_probe_that_does_not_touch_fails_clearly_and_stays_where_the_board_stopped(
    both: tuple[Running, Rpc], machine: str
) -> None:
    hostd, rpc = both
    sim = sim_of(hostd, machine)
    touch(hostd, machine)  # works when touched, but no plate is under the bit
    err = await fails(
        1005, rpc.call("machine.probe", machine=machine, kind="z", plate=PLATE, **FAST)
    )
    assert "did not touch within 10 mm" in err.message and "ALARM" in err.message
    assert "Z-10.000 (machine, mm)" in err.message  # where it stopped
    assert sim.position["z"] == pytest.approx(-10.0)  # the end of its travel
    assert moves_sent(hostd, machine)[-1] == b"G38.2 Z-10 F600"  # nothing after it
    snap = await rpc.call("machine.status", machine=machine)
    assert snap["state"]["name"] == "ALARM"
    assert snap["probe"]["ok"] is False


@pytest.mark.parametrize("machine", MACHINES)
async def test_a_probe_is_refused_during_a_job_and_moves_nothing(
    both: tuple[Running, Rpc], machine: str
) -> None:
    hostd, rpc = both
    sim_of(hostd, machine).touch_plate(TouchPlate(top=TOP))
    job = await rpc.call("machine.jog", machine=machine, axes={"x": 200}, feed=100)
    touch(hostd, machine)
    err = await fails(1003, rpc.call("machine.probe", machine=machine, kind="z", plate=PLATE))
    assert "idle" in err.message
    await rpc.call("machine.jog_stop", machine=machine)
    await job_end(rpc, job["job"])
    assert not any(line.startswith(b"G38") for line in lines_sent(hostd, machine))


async def test_a_probe_is_refused_in_an_alarm_with_the_lockout_code(
    both: tuple[Running, Rpc],
) -> None:
    hostd, rpc = both
    await rpc.call("machine.alarm", machine=G2)
    await rpc.call("subscribe", topics=["status"], machine=G2)
    while (await rpc.call("machine.status", machine=G2))["state"]["name"] != "ALARM":
        await rpc.notification(lambda n: n["method"] == "status")
    touch(hostd, G2)
    await fails(204, rpc.call("machine.probe", machine=G2, kind="z", plate=PLATE, **FAST))
    assert not any(line.startswith(b"G38") for line in lines_sent(hostd, G2))


async def test_grbl_refuses_a_probe_in_its_alarm(both: tuple[Running, Rpc]) -> None:
    hostd, rpc = both
    sim = sim_of(hostd, GRBL)
    touch(hostd, GRBL)
    await fails(1005, rpc.call("machine.probe", machine=GRBL, kind="z", plate=PLATE, **FAST))
    touch(hostd, GRBL)  # ALARM:5 now: a second probe is refused before it reads the input
    err = await fails(204, rpc.call("machine.probe", machine=GRBL, kind="z", plate=PLATE))
    assert "ALARM" in err.message
    assert sim.position["z"] == pytest.approx(-10.0)


async def test_a_board_with_no_probe_input_refuses_the_probe(both: tuple[Running, Rpc]) -> None:
    hostd, rpc = both
    await rpc.call("settings.set", machine=G2, values={"prbin": 0})
    err = await fails(-32602, rpc.call("machine.probe", machine=G2, kind="z", plate=PLATE))
    assert "prbin" in err.message
    assert moves_sent(hostd, G2) == []


async def test_a_board_that_cannot_show_its_input_probes_only_once_confirmed(
    both: tuple[Running, Rpc],
) -> None:
    """g2core's prbin input forwarded to no `in<n>` reader answers its GET null (gpio.h),
    while G38.2 still reads the pin: the operator's `confirmed` stands in for the check."""
    hostd, rpc = both
    sim = sim_of(hostd, G2)
    assert isinstance(sim, SimController)
    sim.unexpose_input(5)  # prbin's input
    sim.touch_plate(TouchPlate(top=TOP))
    err = await fails(
        -32602, rpc.call("machine.probe", machine=G2, kind="z", plate=PLATE, wait=0.5, **FAST)
    )
    assert "does not show its probe input" in err.message and "confirmed" in err.message
    assert moves_sent(hostd, G2) == []
    result = await rpc.call(
        "machine.probe", machine=G2, kind="z", plate=PLATE, confirmed=True, **FAST
    )
    assert result == {"position": {"z": pytest.approx(TOP)}, "zeroed": ["z"]}
    snap = await rpc.call("machine.status", machine=G2)
    assert snap["work_position"]["z"] == pytest.approx(PLATE + 2.0, abs=0.001)
    assert snap["supervisor"] == "idle"


async def test_confirmed_does_not_stand_in_where_the_board_shows_its_input(
    both: tuple[Running, Rpc],
) -> None:
    """On a board that shows its input, confirmed changes nothing: it must be seen."""
    hostd, rpc = both
    sim_of(hostd, G2).touch_plate(TouchPlate(top=TOP))
    params = {"kind": "z", "plate": PLATE, "wait": 0.5, "confirmed": True, **FAST}
    err = await fails(1003, rpc.call("machine.probe", machine=G2, **params))
    assert "not seen working" in err.message
    assert moves_sent(hostd, G2) == []


@pytest.mark.parametrize(
    "params",
    [
        {"kind": "q", "plate": 10.0},
        {"kind": "z", "plate": -1.0},
        {"kind": "z", "plate": "10"},
        {"kind": "z"},  # no plate given and none configured
        {"kind": "xyz", "plate": 10.0},  # no tool_diameter
        {"kind": "z", "plate": 10.0, "feed": 0.0},
        {"kind": "z", "plate": 10.0, "wait": 1000.0},
        {"kind": "z", "plate": 10.0, "confirmed": "yes"},
    ],
)
async def test_bad_probe_params_are_refused(
    both: tuple[Running, Rpc], params: dict[str, object]
) -> None:
    hostd, rpc = both
    await fails(-32602, rpc.call("machine.probe", machine=G2, **params))
    assert moves_sent(hostd, G2) == []


async def test_the_plate_and_feeds_come_from_the_machines_config(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(probing, "SETTLE", 0.0)
    probe = {"plate": 5.0, "feed": 600.0, "max_travel": 8.0, "retract": 1.0}
    async with running_daemon(tmp_path, probe=probe) as hostd:
        rpc = await hostd.client()
        await hostd.idle(rpc)
        sim = sim_of(hostd, "sim1")
        sim.touch_plate(TouchPlate(top=TOP))
        sim.touch(reads=2)
        result = await asyncio.wait_for(rpc.call("machine.probe", machine="sim1", kind="z"), 15)
        assert result["position"]["z"] == pytest.approx(TOP)
        assert b"G38.2 Z-8 F600" in lines_sent(hostd, "sim1")
        snap = await rpc.call("machine.status", machine="sim1")
        assert snap["work_position"]["z"] == pytest.approx(5.0 + 1.0, abs=0.001)
        await rpc.close()


def assert_zeroed_over_the_plate(snap: dict[str, Any]) -> None:
    """An xyz probe's end on the simulated plate, started at machine 0: back over the
    plate where it started, the work's edges behind the walls (a plate's thickness on
    from their faces: X0 and Y0 at machine 7.5), Z0 the plate's top less its height."""
    assert snap["machine_position"]["x"] == pytest.approx(0.0, abs=0.001)
    assert snap["machine_position"]["y"] == pytest.approx(0.0, abs=0.001)
    assert snap["work_position"]["x"] == pytest.approx(-7.5, abs=0.001)
    assert snap["work_position"]["y"] == pytest.approx(-7.5, abs=0.001)
    assert snap["work_position"]["z"] == pytest.approx(PLATE + 2.0, abs=0.001)
