"""Every row of the fault table through a real daemon and socket, its signals from the sim."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio

from hostd.protocol.states import MachineState
from hostd.sim import SimController
from tests.daemon.conftest import Rpc, RpcFailure, Running, running_daemon

pytestmark = pytest.mark.asyncio

SIGNALS = {
    "lid_open": {"key": "in1", "equals": 1},
    "main_laser": {"key": "in2", "equals": 1},
    "visible_laser": {"key": "in3", "equals": 1},
    "coolant_flow_low": {"key": "ain1", "below": 1.0},
    "coolant_temp_high": {"key": "ain2", "above": 30.0},
}
LONG = "".join(f"G1 X{i % 40} Y{i % 9} F600\n" for i in range(400))


async def fault_became(rpc: Rpc, fault_id: str, active: bool) -> dict[str, Any]:
    """Until the fault topic says this fault became (in)active: the fault."""
    note = await rpc.notification(
        lambda n: (
            n["method"] == "fault"
            and n["params"]["fault"]["id"] == fault_id
            and n["params"]["fault"]["active"] is active
        )
    )
    fault: dict[str, Any] = note["params"]["fault"]
    return fault


class Laser:
    def __init__(self, hostd: Running, rpc: Rpc) -> None:
        self.hostd, self.rpc = hostd, rpc
        self.sim: SimController = hostd.daemon.sims["sim1"]

    async def fault(self, fault_id: str, active: bool) -> dict[str, Any]:
        """Until the fault topic says this fault became (in)active."""
        return await fault_became(self.rpc, fault_id, active)

    async def indicator(self) -> str:
        snapshot = await self.rpc.call("machine.status", machine="sim1")
        indicator: str = snapshot["indicator"]
        return indicator

    async def start(self, name: str = "long.gcode", text: str = LONG) -> int:
        await self.rpc.call("file.upload", name=name, data=text)
        started = await self.rpc.call("job.start", machine="sim1", file=name)
        job_id: int = started["job"]
        return job_id

    async def refused_start(self) -> RpcFailure:
        await self.rpc.call("file.upload", name="short.gcode", data="G0 X1\n")
        with pytest.raises(RpcFailure) as err:
            await self.rpc.call("job.start", machine="sim1", file="short.gcode")
        return err.value

    async def job_end(self, job_id: int) -> dict[str, Any]:
        note = await self.rpc.notification(
            lambda n: (
                n["method"] == "job"
                and n["params"]["job"]["id"] == job_id
                and n["params"]["job"]["state"] not in ("running", "paused")
            )
        )
        job: dict[str, Any] = note["params"]["job"]
        return job


@pytest_asyncio.fixture
async def laser(tmp_path: Path) -> AsyncIterator[Laser]:
    async with running_daemon(tmp_path, signals=SIGNALS) as hostd:
        rpc = await hostd.client()
        await hostd.idle(rpc)
        await rpc.call("subscribe", topics=["fault", "job"], machine="sim1")
        laser = Laser(hostd, rpc)
        laser.sim.set_analog(1, 3.0)  # coolant flowing: an unpowered flow meter reads 0
        faults = await rpc.call("fault.list", machine="sim1")
        if any(f["id"] == "water_flow" and f["active"] for f in faults):
            await laser.fault("water_flow", False)
        yield laser
        await rpc.close()


async def fails(code: int, call: Any) -> RpcFailure:
    with pytest.raises(RpcFailure) as err:
        await call
    assert err.value.code == code, err.value
    return err.value


async def test_the_table_lists_every_fault_inactive_at_first(laser: Laser) -> None:
    faults = await laser.rpc.call("fault.list", machine="sim1")
    assert [f["id"] for f in faults] == [
        "estop",
        "lid_open",
        "lid_closed",
        "water_flow",
        "water_temp",
        "serial",
        "lexical",
        "syntax",
        "underflow",
        "internal",
    ]
    assert not any(f["active"] for f in faults)
    assert {f["id"]: f["severity"] for f in faults}["water_flow"] == "hardware"
    # How each ends (an addition to api.md's fault object), as the table in
    # docs/operations.md says: the dashboard offers Clear by it.
    assert {f["id"]: f["clears"] for f in faults} == {
        "estop": "signal",
        "lid_open": "signal",
        "lid_closed": "signal",
        "water_flow": "signal",
        "water_temp": "signal",
        "serial": "software",
        "lexical": "software",
        "syntax": "reset",
        "underflow": "software",
        "internal": "reset",
    }
    assert await laser.indicator() == "normal"


async def test_lid_open_with_the_main_laser_blocks_jobs_until_overridden(laser: Laser) -> None:
    laser.sim.set_input(2, 1)  # main laser selected
    laser.sim.set_input(1, 1)  # lid open
    fault = await laser.fault("lid_open", True)
    assert (fault["severity"], fault["overridable"], fault["overridden"]) == ("job", True, False)
    assert fault["since"] is not None
    assert await laser.indicator() == "alert"
    err = await laser.refused_start()
    assert err.code == 1007 and err.data == ["lid_open"]
    err = await fails(-32602, laser.rpc.call("fault.clear", machine="sim1", fault="lid_open"))
    assert "condition" in err.message
    over = await laser.rpc.call("fault.override", machine="sim1", fault="lid_open", override=True)
    assert over["overridden"] and over["active"]
    assert await laser.indicator() == "warning"
    job_id = await laser.start("ok.gcode", "G0 X1\n")  # overridden: allowed
    assert (await laser.job_end(job_id))["state"] == "completed"
    laser.sim.set_input(1, 0)  # lid closed
    await laser.fault("lid_open", False)
    assert await laser.indicator() == "normal"


async def test_lid_closed_with_the_visible_laser_is_only_reported(laser: Laser) -> None:
    laser.sim.set_input(3, 1)  # visible laser, lid closed (in1 = 0)
    fault = await laser.fault("lid_closed", True)
    assert fault["severity"] == "recoverable"
    assert await laser.indicator() == "alert"
    job_id = await laser.start("ok.gcode", "G0 X1\n")  # recoverable: not blocking
    assert (await laser.job_end(job_id))["state"] == "completed"
    laser.sim.set_input(1, 1)  # lid opened: cleared
    await laser.fault("lid_closed", False)


async def test_coolant_flow_stops_a_running_job_with_1007(laser: Laser) -> None:
    laser.sim.set_analog(1, 3.0)
    job_id = await laser.start()
    await laser.sim.wait_state(MachineState.RUN)
    laser.sim.set_analog(1, 0.2)  # flow below the minimum
    fault = await laser.fault("water_flow", True)
    assert fault["severity"] == "hardware"
    # Its value is the reading that raised it (behaviour.md: each fault has a value).
    assert fault["value"] == pytest.approx(0.2)
    assert fault["message"] == "coolant flow low (0.2)"
    job = await laser.job_end(job_id)
    assert job["state"] == "failed"
    assert job["error"]["code"] == 1007 and "water_flow" in job["error"]["message"]
    await laser.sim.wait_received(lambda: any(r.data == b"%" for r in laser.sim.received))
    assert [r.data for r in laser.sim.received if r.kind == "realtime"][-2:] == [b"!", b"%"]
    laser.sim.set_analog(1, 3.0)
    await laser.fault("water_flow", False)


async def test_coolant_temperature_is_a_hardware_fault_that_can_be_overridden(
    laser: Laser,
) -> None:
    laser.sim.set_analog(2, 35.0)
    await laser.fault("water_temp", True)
    assert (await laser.refused_start()).data == ["water_temp"]
    # Only a JSON true overrides a safety fault: "false" and 1 were read as false and true.
    for lax in ("false", "true", 1):
        await fails(
            -32602,
            laser.rpc.call("fault.override", machine="sim1", fault="water_temp", override=lax),
        )
    assert (await laser.refused_start()).data == ["water_temp"]
    await laser.rpc.call("fault.override", machine="sim1", fault="water_temp", override=True)
    job_id = await laser.start("ok.gcode", "G0 X1\n")
    assert (await laser.job_end(job_id))["state"] == "completed"
    laser.sim.set_analog(2, 20.0)
    assert (await laser.fault("water_temp", False))["overridden"] is True


async def test_estop_cannot_be_overridden_or_cleared_by_software(laser: Laser) -> None:
    laser.sim.estop(True)
    await laser.fault("estop", True)
    await fails(
        -32602, laser.rpc.call("fault.override", machine="sim1", fault="estop", override=True)
    )
    err = await fails(-32602, laser.rpc.call("fault.clear", machine="sim1", fault="estop"))
    assert "released" in err.message
    laser.sim.estop(False)
    await laser.rpc.call("machine.clear", machine="sim1")
    await laser.fault("estop", False)


async def test_line_noise_is_a_serial_fault_cleared_by_software(laser: Laser) -> None:
    laser.sim.inject_garbage(b"\xff\xfe\x01 noise\n")
    fault = await laser.fault("serial", True)
    assert isinstance(fault["value"], int) and fault["value"] > 0  # lines processed before it
    assert (await laser.refused_start()).data == ["serial"]
    await fails(
        -32602, laser.rpc.call("fault.override", machine="sim1", fault="serial", override=True)
    )
    cleared = await laser.rpc.call("fault.clear", machine="sim1", fault="serial")
    assert cleared["active"] is False
    assert await laser.indicator() == "normal"


async def test_unparseable_output_is_a_lexical_fault(laser: Laser) -> None:
    laser.sim.inject_garbage(b'{"r":{"broken"\n')
    await laser.fault("lexical", True)
    await laser.rpc.call("fault.clear", machine="sim1", fault="lexical")
    await laser.fault("lexical", False)


async def test_a_daemon_line_refused_as_malformed_is_syntax_cleared_only_by_reset(
    laser: Laser,
) -> None:
    engine = laser.hostd.daemon.machines["sim1"].engine
    laser.sim.stop_reading()  # the board leaves our status query unread...
    engine.query_status()
    laser.sim.inject_garbage(b'{"r":{},"f":[1,111,13]}\n')  # ...and it is answered 111
    await laser.fault("syntax", True)
    laser.sim.resume_reading()
    err = await fails(-32602, laser.rpc.call("fault.clear", machine="sim1", fault="syntax"))
    assert "reset" in err.message
    await laser.rpc.call("machine.reset", machine="sim1")
    await laser.fault("syntax", False)


async def test_a_starved_planner_mid_job_is_an_underflow(laser: Laser) -> None:
    short = "".join(f"G1 X{i % 2 * 0.01:.2f} F6000\n" for i in range(200))
    laser.sim.set_ack_delay(0.05)  # answers too slow for moves this short
    job_id = await laser.start("short.gcode", short)
    fault = await laser.fault("underflow", True)
    assert fault["severity"] == "job"
    job = await laser.job_end(job_id)
    assert job["state"] == "failed" and job["error"]["code"] == 1007
    laser.sim.set_ack_delay(0)
    await laser.rpc.call("fault.clear", machine="sim1", fault="underflow")


async def test_an_internal_fault_stops_writing_until_reset(
    laser: Laser, monkeypatch: pytest.MonkeyPatch
) -> None:
    engine = laser.hostd.daemon.machines["sim1"].engine

    def broken(report: dict[str, Any]) -> None:
        raise RuntimeError("invariant broken")

    monkeypatch.setattr(engine.session, "_on_status", broken)  # a bug in the daemon, not the link
    await laser.rpc.call("machine.send", machine="sim1", line="G0 X5")  # moves: reports come
    await laser.fault("internal", True)
    monkeypatch.undo()
    err = await fails(1007, laser.rpc.call("machine.send", machine="sim1", line="{xvm:n}"))
    assert "reset" in err.message
    assert await laser.rpc.call("machine.feedhold", machine="sim1") == {}  # stopping still goes
    await fails(-32602, laser.rpc.call("fault.clear", machine="sim1", fault="internal"))
    await laser.rpc.call("machine.reset", machine="sim1")
    await laser.fault("internal", False)
    assert (await laser.rpc.call("machine.send", machine="sim1", line="{xvm:n}"))["status"] == 0


async def test_no_signals_configured_no_signal_faults(tmp_path: Path) -> None:
    async with running_daemon(tmp_path) as hostd:
        rpc = await hostd.client()
        await hostd.idle(rpc)
        sim = hostd.daemon.sims["sim1"]
        sim.set_input(1, 1)
        sim.set_analog(1, 0.0)
        await rpc.call("machine.send", machine="sim1", line="G0 X1")
        await asyncio.sleep(0.3)  # reports come and go; none may raise a fault
        faults = await rpc.call("fault.list", machine="sim1")
        assert not any(f["active"] for f in faults)
        await rpc.close()
