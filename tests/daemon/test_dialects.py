"""One daemon, one API, two dialects: a g2core board and a grbl laser side by side.

Both are simulated boards on real ptys, reached through the real Unix
socket; every call below is the same for both, but the lines on the wire.
"""

from __future__ import annotations

import pytest

from tests.daemon.conftest import G2, GRBL, Rpc, Running
from tests.daemon.test_api import _drained, fails, job_end

pytestmark = pytest.mark.asyncio

MACHINES = (G2, GRBL)  # sim1 speaks g2core, sim2 grbl (`both`, tests/daemon/conftest.py)


async def test_each_machine_says_its_dialect(both: tuple[Running, Rpc]) -> None:
    _, rpc = both
    listed = {m["id"]: m for m in await rpc.call("machine.list")}
    assert listed["sim1"]["dialect"] == "g2core" and listed["sim2"]["dialect"] == "grbl"
    grbl = await rpc.call("machine.status", machine="sim2")
    assert grbl["board_state"] == "Idle" and grbl["laser_mode"] is True
    assert grbl["state"]["name"] == "READY" and grbl["supervisor"] == "idle"


@pytest.mark.parametrize("machine", MACHINES)
async def test_the_same_job_runs_on_both(both: tuple[Running, Rpc], machine: str) -> None:
    _, rpc = both
    program = "".join(f"G1 X{i % 10} Y{i % 3} F6000 (pass {i})\n" for i in range(300))
    await rpc.call("file.upload", name="square.nc", data="G21 G90\n" + program)
    await rpc.call("subscribe", topics=["job"], machine=machine)
    started = await rpc.call("job.start", machine=machine, file="square.nc")
    done = await job_end(rpc, started["job"])
    assert done["state"] == "completed" and done["lines_acked"] == 301


@pytest.mark.parametrize("machine", MACHINES)
async def test_pause_resume_and_cancel_on_both(both: tuple[Running, Rpc], machine: str) -> None:
    hostd, rpc = both
    await rpc.call("file.upload", name="long.nc", data="G1 X100 F600\nG1 X0\n" * 20)
    await rpc.call("subscribe", topics=["job"], machine=machine)
    started = await rpc.call("job.start", machine=machine, file="long.nc")
    assert (await rpc.call("job.pause", machine=machine))["state"] == "paused"
    assert (await rpc.call("job.resume", machine=machine))["state"] == "running"
    cancelled = await rpc.call("job.cancel", machine=machine)
    assert cancelled["state"] == "cancelled"
    done = await job_end(rpc, started["job"])
    assert done["state"] == "cancelled"
    await hostd.idle(rpc, machine)  # the board rests again (g2core: out of its hold)
    assert (await rpc.call("machine.send", machine=machine, line="G0 X1"))["status"] == 0


async def test_settings_by_the_boards_own_names(both: tuple[Running, Rpc]) -> None:
    _, rpc = both
    assert (await rpc.call("settings.get", machine="sim2", keys=["32", "110"])) == {
        "32": 1,
        "110": 500,
    }
    assert await rpc.call("settings.set", machine="sim2", values={"110": 750}) == {"110": 750}
    assert (await rpc.call("settings.get", machine="sim2", keys=["110"])) == {"110": 750}
    err = await fails(-32602, rpc.call("settings.get", machine="sim2", keys=["xvm"]))
    assert "name it by its number" in err.message


async def test_a_line_grbl_would_misread_never_reaches_it(both: tuple[Running, Rpc]) -> None:
    hostd, rpc = both
    # A comment goes before the line is written: grbl would hold on its '!'.
    assert (await rpc.call("machine.send", machine="sim2", line="G0 X1 (go!)"))["status"] == 0
    err = await fails(-32602, rpc.call("machine.send", machine="sim2", line="G0 X1 !"))
    assert err.data["refusal"] == "realtime" and "realtime" in err.message
    sim = hostd.daemon.sims["sim2"]
    assert not any(r.kind == "realtime" and r.data == b"!" for r in sim.received)


async def test_overrides_reach_a_grbl_board_within_its_steps(
    both: tuple[Running, Rpc],
) -> None:
    _, rpc = both
    await rpc.call("subscribe", topics=["status"], machine="sim2")
    got = await rpc.call("machine.override", machine="sim2", feed=120, rapid=50, spindle=80)
    assert got == {"feed": 120, "spindle": 80, "rapid": 50}  # as the board reports them now
    want = {"feed": 120, "rapid": 50, "spindle": 80}
    await rpc.notification(
        lambda n: n["method"] == "status" and n["params"]["snapshot"]["overrides"] == want
    )
    err = await fails(-32602, rpc.call("machine.override", machine="sim2", feed=250))
    assert "10 to 200" in err.message
    err = await fails(-32602, rpc.call("machine.override", machine="sim2", rapid=75))
    assert "100, 50 or 25" in err.message


async def test_the_host_opens_a_grbl_boards_safety_door(both: tuple[Running, Rpc]) -> None:
    _, rpc = both
    assert await rpc.call("machine.safety_door", machine="sim2") == {}
    await rpc.call("subscribe", topics=["status"], machine="sim2")
    await rpc.notification(
        lambda n: (
            n["method"] == "status"
            and str(n["params"]["snapshot"]["board_state"]).startswith("Door")
        )
    )
    err = await fails(-32602, rpc.call("machine.safety_door", machine="sim1"))
    assert "no safety-door command" in err.message


async def test_a_grbl_console_without_status_traffic_leaves_out_the_daemons_modes_poll(
    both: tuple[Running, Rpc],
) -> None:
    """After a client's G-code line the daemon asks grbl `$G` (its modes are reported
    nowhere else). An operator whose console leaves out status traffic (the dashboard's
    *status reports* box unticked) did not send that `$G` and sees none of it: not the
    line, not its `[GC:...]`, not its `ok`. A `$G` the operator typed is shown, with
    its answer, like any line they sent."""
    running, rpc = both
    quiet = await running.client()
    try:
        await rpc.call("subscribe", topics=["console"], machine=GRBL)
        await quiet.call("subscribe", topics=["console"], machine=GRBL, status_traffic=False)
        # No move: grbl answers `$I` only at rest (error:8 while one runs).
        await rpc.call("machine.send", machine=GRBL, line="G21")  # then the daemon's `$G`
        await rpc.call("machine.send", machine=GRBL, line="$G")  # the operator's
        await rpc.call("machine.send", machine=GRBL, line="$I")  # where both are cut
        full = await _drained(rpc, until="[OPT:")
        kept = await _drained(quiet, until="[OPT:")
    finally:
        await quiet.close()
    texts = [(n["direction"], n["text"]) for n in full]
    assert texts.count(("tx", "$G")) == 2, texts  # the daemon's, then the operator's
    own = texts.index(("tx", "$G"))
    modes = next(i for i in range(own, len(texts)) if texts[i][1].startswith("[GC:"))
    answer = texts.index(("rx", "ok"), modes)
    assert texts.index(("tx", "G21")) < own  # the poll follows the line it is for

    def status(i: int) -> bool:
        direction, text = texts[i]
        return text == "?" if direction == "tx" else text.startswith("<")

    expected = [n for i, n in enumerate(full) if i not in (own, modes, answer) and not status(i)]
    assert kept == expected
    shown = [(n["direction"], n["text"]) for n in kept]
    assert ("tx", "$G") in shown and any(t.startswith("[GC:") for _, t in shown)
    assert ("tx", "G21") in shown
