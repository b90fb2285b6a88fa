"""Issue 24 through the real socket: maintenance commands are deliberate, files are
checked before anything moves.

A g2core board (sim1) and a grbl board (sim2), simulated on real ptys; every
refusal is checked to have left nothing on the board's wire (`sim.received`).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.daemon.conftest import G2, GRBL, Rpc, Running, running_daemon
from tests.daemon.test_api import fails, job_end

pytestmark = pytest.mark.asyncio


def reached(hostd: Running, machine: str, text: str) -> bool:
    return any(text.encode() in r.data for r in hostd.daemon.sims[machine].received)


@pytest.mark.parametrize(
    ("machine", "line", "kind"),
    [
        (GRBL, "$RST=*", "restore"),
        (GRBL, "$ rst = $", "restore"),
        (GRBL, "$N0=G0X-100", "startup-block"),
        (GRBL, "$N1=", "startup-block"),
        (GRBL, "$SLP", "sleep"),
        (GRBL, "$I=mine", "build-info"),
        (GRBL, "$J=G91 X9999999999 F100", "absurd-jog"),
        (GRBL, "$J=G91 X400 F100", "absurd-jog"),  # the sim's X travels 300 mm ($130)
        (G2, "{defa:1}", "restore"),
        (G2, '{"flash":true}', "bootloader"),
    ],
)
async def test_machine_send_refuses_maintenance_commands(
    both: tuple[Running, Rpc], machine: str, line: str, kind: str
) -> None:
    hostd, rpc = both
    err = await fails(-32602, rpc.call("machine.send", machine=machine, line=line))
    assert err.data == {"refusal": "maintenance", "maintenance": kind}
    assert "machine.send refuses it" in err.message
    assert not reached(hostd, machine, line)
    # An ordinary line still goes.
    assert (await rpc.call("machine.send", machine=machine, line="G0 X1"))["status"] == 0


async def test_a_sane_jog_and_the_views_still_pass(both: tuple[Running, Rpc]) -> None:
    _, rpc = both
    # `$N` first: grbl answers it only at rest (error:8 while the jog runs).
    found = await rpc.call("machine.send", machine=GRBL, line="$N")
    assert found["r"]["lines"] == ["$N0=", "$N1="]
    assert (await rpc.call("machine.send", machine=GRBL, line="$J=G91 X-5 F600"))["status"] == 0
    status = await rpc.call("machine.status", machine=GRBL)
    assert status["startup_blocks"] == []  # read at connect: none stored


async def test_machine_maintenance_needs_the_machines_opt_in(both: tuple[Running, Rpc]) -> None:
    hostd, rpc = both
    err = await fails(-32602, rpc.call("machine.maintenance", machine=GRBL, line="$RST=$"))
    assert "maintenance = true" in err.message and err.data["maintenance"] == "restore"
    assert not reached(hostd, GRBL, "$RST")
    err = await fails(-32602, rpc.call("machine.maintenance", machine=GRBL, line="G0 X1"))
    assert "not a maintenance command" in err.message


async def test_machine_maintenance_sends_on_purpose_where_allowed(tmp_path: Path) -> None:
    grbl = {"dialect": "grbl", "maintenance": True}
    async with running_daemon(tmp_path, machines=2, per_machine=[{"maintenance": True}, grbl]) as d:
        rpc = await d.client()
        await d.idle(rpc, GRBL)
        # The simulated grbl has no $SLP: it answers error:3, which shows the line went.
        err = await fails(1005, rpc.call("machine.maintenance", machine=GRBL, line="$SLP"))
        assert err.data["status"] == 3
        assert reached(d, GRBL, "$SLP")
        # Never on purpose: an absurd jog, g2core's bootloader and factory defaults.
        for machine, line in ((GRBL, "$J=G91 X99999 F100"), (G2, "{defa:1}"), (G2, "{flash:1}")):
            err = await fails(-32602, rpc.call("machine.maintenance", machine=machine, line=line))
            assert "it is never sent" in err.message
        await rpc.close()


# -- files checked at job.start (part 4) -----------------------------------------------


@pytest.mark.parametrize(
    ("machine", "program", "kind", "line"),
    [
        (GRBL, "G21\nG1 X1 F100 (" + "x" * 200 + ")\nG0 X1" + " Y1" * 50 + "\n", "unsendable", 3),
        (GRBL, "G21\nT2 M6\nG0 X1\n", "tool-change", 2),
        (G2, "G21\nG0 X1\nT2 M06\n", "tool-change", 3),
        (GRBL, "G21\nG0 X1\nG43 H1 Z5\n", "unsupported", 3),
        (G2, "G21\nG81 X1 Y1 Z-2 R1 F100\n", "unsupported", 2),
        (GRBL, "G21\n$RST=*\n", "maintenance", 2),
        (G2, "G21\nG0 X1" + " " * 520 + "Y1\n", "unsendable", 2),
    ],
)
async def test_job_start_refuses_what_the_board_would_refuse_with_line_numbers(
    both: tuple[Running, Rpc], machine: str, program: str, kind: str, line: int
) -> None:
    hostd, rpc = both
    await rpc.call("file.upload", name="bad.nc", data=program)
    before = len(hostd.daemon.sims[machine].received)
    err = await fails(1008, rpc.call("job.start", machine=machine, file="bad.nc"))
    assert err.data["problems"][0] == {
        "line": line,
        "kind": kind,
        "text": err.data["problems"][0]["text"],
    }
    assert f"line {line}:" in err.message and err.data["problems_total"] == 1
    # Queries only (status requests, the board's settings and modes), never a job line.
    sent = hostd.daemon.sims[machine].received[before:]
    assert all(r.data.startswith((b"?", b"$", b"{")) for r in sent), sent
    assert not any(b"G0 X1" in r.data or b"G21" in r.data for r in sent)
    report = await rpc.call("file.analyze", file="bad.nc", machine=machine)
    assert report["problems"] == err.data["problems"]
    status = await rpc.call("machine.status", machine=machine)
    assert status["job"] is None or status["job"]["file"] != "bad.nc"  # no job was made


async def test_a_line_that_fits_only_unnumbered_runs_on_a_default_grbl(
    both: tuple[Running, Rpc],
) -> None:
    """The simulated grbl is classic's default build (`[OPT:V,15,128]`: no line numbers),
    so job lines go as the file has them, and the check reads them so: a line whose LF is
    the 127th byte runs. Numbered (`N2 `) it would not fit, and would be refused."""
    hostd, rpc = both
    text = "G0 X1" + " " * 119 + "Y1"  # 126 bytes, and its LF
    await rpc.call("file.upload", name="long.nc", data=f"G21\n{text}\nG0 X0 Y0\n")
    assert (await rpc.call("file.analyze", file="long.nc", machine=GRBL))["problems"] == []
    await rpc.call("subscribe", topics=["job"], machine=GRBL)
    started = await rpc.call("job.start", machine=GRBL, file="long.nc")
    assert (await job_end(rpc, started["job"]))["state"] == "completed"
    written = b"".join(r.data for r in hostd.daemon.sims[GRBL].received)
    assert text.encode() + b"\n" in written and b"N2" not in written


async def test_force_starts_a_refused_file_anyway(both: tuple[Running, Rpc]) -> None:
    _, rpc = both
    await rpc.call("file.upload", name="tools.nc", data="G21\nT2 M6\nG0 X1\n")
    await fails(1008, rpc.call("job.start", machine=G2, file="tools.nc"))
    await rpc.call("subscribe", topics=["job"], machine=G2)
    started = await rpc.call("job.start", machine=G2, file="tools.nc", force=True)
    assert (await job_end(rpc, started["job"]))["state"] == "completed"


# -- grbl startup blocks and hostd's own reset (part 3) -------------------------------


async def grbl_with_a_moving_startup_block(d: Running) -> Rpc:
    rpc = await d.client()
    await d.idle(rpc, GRBL)
    stored = await rpc.call("machine.maintenance", machine=GRBL, line="$N0=G0 X-5")
    assert stored["status"] == 0
    await d.idle(rpc, GRBL)  # storing ran the block once (grbl system.c)
    blocks = (await rpc.call("machine.status", machine=GRBL))["startup_blocks"]
    assert blocks == [{"n": 0, "line": "G0X-5", "acts": "moves the machine (G0)"}]
    return rpc


async def cancel_a_job(rpc: Rpc) -> None:
    await rpc.call("file.upload", name="long.nc", data="G1 X-100 F600\nG1 X0\n" * 20)
    await rpc.call("subscribe", topics=["job", "exception"], machine=GRBL)
    started = await rpc.call("job.start", machine=GRBL, file="long.nc")
    await rpc.notification(lambda n: n["method"] == "job" and n["params"]["job"]["lines_acked"] > 0)
    cancelled = await rpc.call("job.cancel", machine=GRBL)
    assert cancelled["id"] == started["job"] and cancelled["state"] == "cancelled"


async def test_a_cancel_holds_the_board_while_a_startup_block_would_move_it(
    tmp_path: Path,
) -> None:
    grbl = {"dialect": "grbl", "maintenance": True}
    async with running_daemon(tmp_path, machines=2, per_machine=[{}, grbl]) as d:
        rpc = await grbl_with_a_moving_startup_block(d)
        sim = d.daemon.sims[GRBL]
        await cancel_a_job(rpc)
        held = await rpc.notification(lambda n: n["method"] == "exception")
        assert "held instead of reset" in held["params"]["report"]["msg"]
        assert "$N0=G0X-5 moves the machine (G0)" in held["params"]["report"]["msg"]
        status = await rpc.call("machine.status", machine=GRBL)
        assert status["supervisor"] == "busy" and status["board_state"] == "Hold:0"
        assert not any(r.data == b"\x18" for r in sim.received)  # no reset of hostd's own
        err = await fails(1003, rpc.call("machine.cycle_start", machine=GRBL))
        assert "machine.reset runs it" in err.message  # `~` would run the cancelled moves
        await fails(1003, rpc.call("machine.send", machine=GRBL, line="G0 X1"))
        # The operator's reset: asked for, it goes, and the block runs.
        await rpc.call("machine.reset", machine=GRBL)
        await d.idle(rpc, GRBL)
        assert any(r.data == b"\x18" for r in sim.received)
        await rpc.close()


async def test_startup_motion_allowed_a_cancel_resets_as_before(tmp_path: Path) -> None:
    grbl = {"dialect": "grbl", "maintenance": True, "startup_motion": True}
    async with running_daemon(tmp_path, machines=2, per_machine=[{}, grbl]) as d:
        rpc = await grbl_with_a_moving_startup_block(d)
        await cancel_a_job(rpc)
        await d.idle(rpc, GRBL)  # reset, re-synced: the block ran, as configured
        assert any(r.data == b"\x18" for r in d.daemon.sims[GRBL].received)
        await rpc.close()


async def test_machine_jog_refuses_a_jog_no_travel_has_room_for(both: tuple[Running, Rpc]) -> None:
    hostd, rpc = both
    # grbl: the travel from `$130` (300 mm on the simulated board).
    err = await fails(-32602, rpc.call("machine.jog", machine=GRBL, axes={"x": -400}, feed=600))
    assert err.data == {"refusal": "maintenance", "maintenance": "absurd-jog"}
    assert "more than the axis travels" in err.message
    assert not reached(hostd, GRBL, "X-400")
    # g2core: no travel in the session; the documented bound, 10,000 mm.
    err = await fails(-32602, rpc.call("machine.jog", machine=G2, axes={"y": 20000}, feed=600))
    assert "beyond any machine's travel" in err.message
    for machine in (GRBL, G2):
        await rpc.call("machine.jog", machine=machine, axes={"x": -5}, feed=600)
