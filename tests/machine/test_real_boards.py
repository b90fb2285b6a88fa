"""What real g2core boards print, produced by the simulator, through the engine (issue 12).

Each test drives the engine over a real pty against the simulated board,
which prints what the firmware prints (synthetos/g2 `g2core/`: the file is
named in each test and in docs/simulator.md); docs/protocol.md names the
rule the engine follows.
"""

from __future__ import annotations

import asyncio
import math

import pytest

from hostd.machine.events import ExceptionRaised, FaultDetected, ProbeReported, StatusChanged
from hostd.machine.stream import JobStream
from hostd.protocol.errors import ControllerError, Rejected
from hostd.protocol.states import MachineState as S
from hostd.protocol.status import Status, message
from hostd.protocol.vocabulary import StreamEnd
from hostd.sim.callsites import CALL_SITES, CallSite
from tests.machine.conftest import Bench, Rig, long_moves

pytestmark = pytest.mark.asyncio

LOCKOUT = {"alarm": S.ALARM, "shutdown": S.SHUTDOWN, "panic": S.PANIC}
REJECTED = {S.ALARM: 204, S.SHUTDOWN: 205, S.PANIC: 206}


def moves(count: int, feed: int = 3000) -> list[str]:
    return [f"G1 X{(i % 40) * 2:.3f} Y{(i % 7) * 2:.3f} F{feed}" for i in range(1, count + 1)]


async def finished(stream: JobStream) -> StreamEnd:
    async with asyncio.timeout(10):
        return (await stream.result).end


def running_job(e: object) -> bool:
    return isinstance(e, StatusChanged) and e.report.get("stat") == S.RUN


def faults(rig: Rig) -> list[str]:
    return [e.fault for e in rig.recorder.events if isinstance(e, FaultDetected)]


# -- item 2: probe reports (cycle_probing.cpp) ------------------------------------


async def test_a_probe_that_touches_reaches_the_snapshot_and_an_event(rig: Rig) -> None:
    rig.sim.probe_surface("z", -1.5)
    assert (await rig.engine.send("G38.2 Z-10 F600")).ok
    event = await rig.recorder.wait_for(lambda e: isinstance(e, ProbeReported))
    assert isinstance(event, ProbeReported)
    assert event.probe["ok"] is True and event.probe["position"]["z"] == -1.5
    assert rig.engine.model.snapshot()["probe"] == event.probe
    assert faults(rig) == []


async def test_a_g38_2_that_never_touches_is_an_alarm_and_a_failed_probe(rig: Rig) -> None:
    await rig.engine.send("G38.2 Z-2 F600")
    event = await rig.recorder.wait_for(lambda e: isinstance(e, ProbeReported))
    assert isinstance(event, ProbeReported) and event.probe["ok"] is False
    async with asyncio.timeout(5):
        await rig.engine.wait_for(lambda: rig.engine.model.state is S.ALARM)
    with pytest.raises(Rejected) as refused:
        await rig.engine.send("G0 X1")
    assert refused.value.code == 204


async def test_a_job_that_probes_runs_on_after_the_probe(rig: Rig) -> None:
    rig.sim.probe_surface("z", -0.75)
    stream = rig.job(["G0 X5", "G38.2 Z-5 F300", "G0 Z5", *moves(10)])
    assert await finished(stream) is StreamEnd.COMPLETED
    assert rig.engine.model.probe is not None and rig.engine.model.probe["ok"] is True
    assert faults(rig) == []


# -- item 5: nan and inf (util.cpp floattoa) --------------------------------------


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
async def test_a_report_the_firmware_prints_nan_in_does_not_stop_a_job(
    rig: Rig, value: float
) -> None:
    stream = rig.job(long_moves(40))  # a job that completes: moves too long to underflow
    await rig.recorder.wait_for(running_job)
    rig.sim.glitch("vel", value)
    await rig.recorder.wait_for(
        lambda e: isinstance(e, StatusChanged) and "vel" in e.report and e.report["vel"] is None
    )
    rig.sim.glitch("vel", None)
    assert await finished(stream) is StreamEnd.COMPLETED
    assert faults(rig) == []


# -- item 6: every exception the firmware raises, from its call site (alarm.cpp) ----


def _site_id(site: CallSite) -> str:
    return f"{site.path}-{site.status}-{site.where}"


@pytest.mark.parametrize("site", CALL_SITES, ids=_site_id)
async def test_every_firmware_lockout_fails_the_job_and_the_engine_reads_its_state(
    rig: Rig, site: CallSite
) -> None:
    stream = rig.job(moves(200, feed=600))
    await rig.recorder.wait_for(running_job)
    rig.sim.firmware_exception(site)
    assert await finished(stream) is StreamEnd.FAILED
    want = LOCKOUT[site.path]
    # 101.06 gets there through the alarm's hold (g2builds.py): the job fails on the
    # exception report, before the board stands in the lockout.
    await rig.sim.wait_state(want)
    # A panic prints no status report; the one the engine asks for after any
    # exception report shows where the board is (92 is raised both ways).
    async with asyncio.timeout(5):
        await rig.engine.wait_for(lambda: rig.engine.model.state is want)
    with pytest.raises(Rejected) as refused:
        await rig.engine.send("G0 X1")
    assert refused.value.code == REJECTED[want]
    assert b"G0 X1" not in rig.received_lines()


async def test_a_panic_printed_as_141_is_a_panic(rig: Rig) -> None:
    # Status 141 has no call site in the source read; hostd classes it with 140.
    rig.sim.firmware_exception(CallSite(141, "panic", "cm_arc_feed() impossible value", "-"))
    async with asyncio.timeout(5):
        await rig.engine.wait_for(lambda: rig.engine.model.state is S.PANIC)


# -- item 4: answers that answer no line --------------------------------------------


async def test_a_failed_homing_books_its_extra_answer_to_no_line(rig: Rig) -> None:
    # cycle_homing.cpp _homing_error_exit: {"r":{"msg":"X axis ..."},"f":[1,240,1]}.
    rig.sim.fail_homing("x", Status.HOMING_ERROR_HOMING_INPUT_MISCONFIGURED)
    assert (await rig.engine.send("G28.2 X0")).ok
    report = await rig.recorder.wait_for(lambda e: isinstance(e, ExceptionRaised))
    assert isinstance(report, ExceptionRaised) and report.report["st"] == 240
    assert report.report["msg"] == f"X axis {message(246)}"
    assert (await rig.engine.send("{xvm:n}")).body == {"xvm": 6000}  # its own answer
    assert (await rig.engine.send("G0 X1")).ok
    async with asyncio.timeout(5):
        await rig.engine.wait_for(lambda: rig.engine.model.homed is False)
    assert not rig.sim.homed
    assert faults(rig) == []


async def test_an_answer_too_long_for_the_board_fails_only_its_own_line(rig: Rig) -> None:
    rig.sim.set_output_buffer(120)  # json_print_response: `{sys:n}` does not fit
    with pytest.raises(ControllerError) as lost:
        await rig.engine.send("{sys:n}")
    assert lost.value.status == Status.JSON_OUTPUT_TOO_LONG
    assert (await rig.engine.send("{xvm:n}")).body == {"xvm": 6000}
    rig.sim.set_output_buffer(512)
    stream = rig.job(long_moves(20))
    assert await finished(stream) is StreamEnd.COMPLETED
    assert faults(rig) == []


async def test_an_answer_the_board_never_printed_is_found_by_the_next_answers_count(
    rig: Rig,
) -> None:
    rig.sim.set_output_buffer(120, reported=False)
    lost = asyncio.create_task(rig.engine.send("{sys:n}"))
    # The board read it (and printed nothing) before the next query goes out: a task
    # started late on a loaded machine would otherwise send it after that answer.
    await rig.sim.wait_received(b'{"sys":null}')
    answer = await rig.engine.send("{si:n}")  # of another length: its count tells
    assert "si" in answer.body
    rig.sim.set_output_buffer(512)
    with pytest.raises(ControllerError, match="never answered"):
        await lost
    assert "sys" in (await rig.engine.send("{sys:n}")).body


async def test_a_job_whose_homing_fails_fails_for_that_reason(bench: Bench) -> None:
    """cycle_homing.cpp answers the G28.2 itself with 0 and reports the failure apart.

    The board would go on to run the moves after it, from an unknown position:
    the job fails naming the homing failure, and the board's queue is killed.
    Holding job lines back after the report is not the planner starving.
    """
    bench.sim.fail_homing("x", Status.HOMING_ERROR_HOMING_INPUT_MISCONFIGURED)
    bench.write("h.gcode", "G28.2 X0\n" + "\n".join(moves(30)) + "\n")
    job = await bench.machine.start_make("h.gcode")
    row = await bench.job_ended(job.id)
    assert row.state == "failed"
    assert row.error is not None and "Homing" in row.error.message
    assert [f.id for f in bench.machine.faults.active()] == []
    assert bench.machine.engine.model.homed is False
