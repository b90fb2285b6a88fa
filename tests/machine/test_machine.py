"""A machine's operations, supervisor and job rows, against the simulated board."""

from __future__ import annotations

import asyncio
import itertools
import math
import time
from pathlib import Path
from typing import Any

import pytest

from hostd.machine.events import JobChanged
from hostd.machine.jobrunner import PUBLISH_EVERY
from hostd.machine.machine import NoSuchFile
from hostd.machine.supervisor import Refused
from hostd.machine.supervisor import State as Sup
from hostd.protocol.settings import set_lines
from hostd.protocol.states import MachineState as S
from tests.machine.conftest import Bench, bench_for, long_moves

pytestmark = pytest.mark.asyncio

MOVES = "".join(f"{line}\n" for line in long_moves(60))  # long enough not to underflow
PROGRAM = "%\n(part)\nG21 G90\n\n" + MOVES
PROGRAM += "M30\n%\n"


async def test_connecting_goes_busy_then_idle(bench: Bench) -> None:
    assert bench.transitions() == [
        ("disconnected", "connect", "busy"),
        ("busy", "went-idle", "idle"),
    ]
    assert bench.machine.snapshot()["supervisor"] == "idle"


async def test_a_make_job_streams_a_file_and_is_recorded(bench: Bench) -> None:
    bench.write("part.gcode", PROGRAM)
    job = await bench.machine.start_make("part.gcode")
    assert (job.kind, job.state, job.file, job.lines_total) == ("make", "running", "part.gcode", 62)
    assert bench.machine.supervisor.state is Sup.OPERATION
    row = await bench.job_ended(job.id)
    assert row.state == "completed"
    assert row.lines_sent == row.lines_acked == row.lines_total == 62
    assert row.ended_at is not None and row.error is None
    await bench.supervisor(Sup.IDLE)
    assert bench.transitions()[2:] == [
        ("idle", "start-operation", "operation"),
        ("operation", "operation-stopped", "busy"),
        ("busy", "went-idle", "idle"),
    ]
    sent = [r.data for r in bench.sim.received if r.kind == "line" and not r.data.startswith(b"{")]
    # Each line carries its file line number, which the board reports back while it runs.
    assert sent[0] == b"N3 G21 G90" and sent[-1].endswith(b" M30") and len(sent) == 62
    assert row.line_executed == int(sent[-1].split()[0][1:])


async def test_start_line_skips_the_lines_before_it(bench: Bench) -> None:
    bench.write("part.gcode", PROGRAM)
    job = await bench.machine.start_make("part.gcode", start_line=60)
    row = await bench.job_ended(job.id)
    assert row.state == "completed"
    assert row.lines_total == row.lines_acked == 6  # file lines 60..63 and M30


async def test_missing_file_is_1004(bench: Bench) -> None:
    with pytest.raises(NoSuchFile) as err:
        await bench.machine.start_make("nope.gcode")
    assert err.value.code == 1004
    assert bench.machine.supervisor.state is Sup.IDLE


async def test_operations_start_only_from_idle(bench: Bench) -> None:
    bench.write("slow.gcode", "".join(f"{line}\n" for line in long_moves(200)))
    job = await bench.machine.start_make("slow.gcode")
    with pytest.raises(Refused) as err:
        await bench.machine.start_make("slow.gcode")
    assert err.value.code == 1003
    with pytest.raises(Refused):
        await bench.machine.jog({"x": 1.0}, 600)
    assert len(await bench.store.list_jobs()) == 1  # nothing half-started
    await bench.machine.cancel()
    assert (await bench.job_ended(job.id)).state == "cancelled"


async def test_pause_and_resume_a_make_job(bench: Bench) -> None:
    told: list[tuple[float, dict[str, Any]]] = []  # every `job` event, when it was told
    unlike: list[tuple[dict[str, Any], dict[str, Any]]] = []  # a tell or snapshot gone stale

    def heard(event: object) -> None:
        if not isinstance(event, JobChanged):
            return
        told.append((time.monotonic(), event.job))
        # The JSON told and snapshotted is made from a dump kept per row (current_json):
        # it is the row as it stands, counts and all, at each tell.
        current = bench.machine.current_job()
        assert current is not None
        now = current.model_dump(mode="json")
        for seen in (event.job, bench.machine.snapshot()["job"]):
            if seen != now:
                unlike.append((seen, now))

    bench.machine.hub.subscribe(heard)
    bench.write("slow.gcode", "".join(f"{line}\n" for line in long_moves(30)))
    job = await bench.machine.start_make("slow.gcode")
    await bench.sim.wait_state(S.RUN)
    paused = bench.machine.pause()
    assert paused.state == "paused"
    assert bench.machine.supervisor.state is Sup.PAUSED
    await bench.sim.wait_state(S.HOLD)
    row = await bench.store.get(job.id)
    async with asyncio.timeout(2):
        while row is not None and row.state != "paused":
            row = await bench.store.get(job.id)
    resumed = bench.machine.resume()
    assert resumed.state == "running"
    assert bench.machine.supervisor.state is Sup.OPERATION
    assert (await bench.job_ended(job.id)).state == "completed"
    # A change of state is told at once; progress at most every PUBLISH_EVERY after the
    # last tell (the follower that wrote the pause's row did not tell it again at once),
    # and never a job the same as the last told. (A bound the code keeps, not a timing.)
    assert [job["state"] for _, job in told].count("paused") >= 1
    assert unlike == []
    for (at, before), (then, job) in itertools.pairwise(told):
        assert job != before
        if job["state"] == before["state"]:
            assert then - at >= PUBLISH_EVERY - 0.005, (before, job)  # (stamped after)


async def test_cancel_kills_the_job_on_the_board(bench: Bench) -> None:
    bench.write("slow.gcode", "".join(f"{line}\n" for line in long_moves(200)))
    await bench.machine.start_make("slow.gcode")
    await bench.sim.wait_state(S.RUN)
    ended = await bench.machine.cancel()
    assert ended.state == "cancelled"
    assert ended.lines_acked <= ended.lines_sent < 200
    assert any(r.data == b"\x04" for r in bench.sim.received)
    await bench.supervisor(Sup.IDLE)


async def test_a_jog_moves_relative_and_restores_absolute(bench: Bench) -> None:
    job = await bench.machine.jog({"x": 1.5, "y": -0.5}, 600)
    row = await bench.job_ended(job.id)
    assert (row.kind, row.state, row.lines_acked) == ("jog", "completed", 2)
    assert bench.sim.position["x"] == pytest.approx(1.5)
    lines = [r.data for r in bench.sim.received if r.kind == "line" and r.data[:1] != b"{"]
    assert lines[-2:] == [b"G91 G1 X1.5000 Y-0.5000 F600.000", b"G90"]


async def test_jog_stop_drops_the_rest_and_still_restores_absolute(bench: Bench) -> None:
    job = await bench.machine.jog({"x": 200}, 300)
    await bench.sim.wait_state(S.RUN)
    bench.machine.jog_stop()
    row = await bench.job_ended(job.id)
    assert row.state == "cancelled"
    await bench.sim.wait_received(lambda: bench.sim.received[-1].data == b"G90")
    assert bench.sim.position["x"] < 200


async def test_settings_are_read_and_written_as_one_operation(bench: Bench) -> None:
    job, bodies = await bench.machine.settings(set_lines({"xvm": 12000, "yvm": 11000}))
    assert bodies == [{"xvm": 12000}, {"yvm": 11000}]
    assert (job.kind, job.lines_total) == ("settings", 2)
    row = await bench.store.get(job.id)
    assert row is not None and (row.state, row.lines_acked) == ("completed", 2)
    _, bodies = await bench.machine.settings(["{xvm:n}"])
    assert bodies == [{"xvm": 12000}]


async def test_an_alarm_mid_job_fails_the_row_and_keeps_the_machine_busy(bench: Bench) -> None:
    bench.write("long.gcode", "".join(f"G1 X{(i % 2) * 10} F3000\n" for i in range(400)))
    job = await bench.machine.start_make("long.gcode")
    await bench.sim.wait_for(lambda: len(bench.sim.received) > 30)
    bench.sim.limit_switch("x")
    row = await bench.job_ended(job.id)
    assert row.state == "failed" and row.error is not None and row.error.code == 204
    assert row.lines_acked <= row.lines_sent < 400
    await bench.supervisor(Sup.BUSY)
    await bench.machine.engine.clear()
    await bench.supervisor(Sup.IDLE)


async def test_unplug_mid_job_interrupts_it_and_replug_brings_the_machine_back(
    tmp_path: Path,
) -> None:
    async with bench_for(tmp_path, auto_connect=True) as bench:
        # Interrupted by the unplug, never failed before it by an underflow: long moves.
        bench.write("long.gcode", "".join(f"{line}\n" for line in long_moves(400)))
        job = await bench.machine.start_make("long.gcode")
        await bench.sim.wait_for(lambda: len(bench.sim.received) > 30)
        await bench.sim.unplug()
        row = await bench.job_ended(job.id)
        assert row.state == "interrupted"
        answered = sum(1 for r in bench.sim.sent if r.data.startswith(b'{"r":{'))
        assert 0 < row.lines_acked <= row.lines_sent
        assert row.lines_acked <= answered  # never more than the controller answered
        await bench.supervisor(Sup.DISCONNECTED)
        await bench.sim.replug()
        await bench.supervisor(Sup.IDLE)  # auto_connect: back through connect


async def test_two_machines_are_independent(tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    async with bench_for(tmp_path / "a", "a") as a, bench_for(tmp_path / "b", "b") as b:
        text = "".join(f"{line}\n" for line in long_moves(40))  # b's must complete
        a.write("a.gcode", text)
        b.write("b.gcode", text)
        job_a = await a.machine.start_make("a.gcode")
        job_b = await b.machine.start_make("b.gcode")
        await a.sim.wait_for(lambda: len(a.sim.received) > 20)
        await a.sim.unplug()
        assert (await a.job_ended(job_a.id)).state == "interrupted"
        assert (await b.job_ended(job_b.id)).state == "completed"


async def test_nan_in_a_report_mid_job_is_no_lexical_fault(bench: Bench) -> None:
    bench.write("part.gcode", PROGRAM)
    job = await bench.machine.start_make("part.gcode")
    await bench.sim.wait_state(S.RUN)
    bench.sim.glitch("vel", math.nan)  # printed bare, as the firmware's floattoa() does
    bench.sim.glitch("feed", math.inf)
    await bench.sim.wait_for(lambda: any(b'"vel":nan' in s.data for s in bench.sim.sent))
    bench.sim.glitch("vel", None)
    bench.sim.glitch("feed", None)
    row = await bench.job_ended(job.id)
    assert row.state == "completed"
    assert [f.id for f in bench.machine.faults.active()] == []
    assert bench.machine.snapshot()["velocity"] is not None  # later reports still read
