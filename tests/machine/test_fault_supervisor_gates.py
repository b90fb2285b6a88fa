"""The fault table and the supervisor as the operator meets them on a whole machine: which
fault stops or refuses a job, what a reset that never reached the board leaves, which
state admits a job, when an operation's move is over, and what a client is told as the
states change.

Each test here guards a rule that a hand mutation campaign on faults.py, supervisor.py,
signals.py, rest.py, machine_core.py and the machine's pause gates found unguarded: with
the rule's line changed every other test still passed. The machine is a real `Machine` on
the simulated g2core (or grbl) over a pty (tests/machine/conftest.py); a test waits for
the event its step causes, never for time to pass.
"""

from __future__ import annotations

import asyncio
import dataclasses
import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

import pytest
from structlog.testing import capture_logs

from hostd.machine import operations
from hostd.machine.events import (
    Console,
    EngineEvent,
    Event,
    FaultChanged,
    JobChanged,
    StatusChanged,
    SupervisorChanged,
)
from hostd.machine.supervisor import Refused
from hostd.machine.supervisor import State as Sup
from hostd.protocol.errors import ControllerError, FaultActive, NotConnected
from hostd.protocol.states import MachineState as S
from tests.machine.conftest import FAST, Bench, bench_for, long_moves
from tests.machine.test_grbl import grbl_bench

pytestmark = pytest.mark.asyncio

LONG = "".join(f"{line}\n" for line in long_moves(200))  # seconds of motion on FAST's board


Seen = Callable[[Event | EngineEvent], bool]


def fault_became(fault_id: str, active: bool) -> Seen:
    """A predicate: the fault topic says this fault became (in)active."""

    def became(e: Event | EngineEvent) -> bool:
        return (
            isinstance(e, FaultChanged)
            and e.fault["id"] == fault_id
            and e.fault["active"] is active
        )

    return became


def reported(key: str, value: float) -> Seen:
    """A predicate: a status report carried `key` at `value` (the machine has judged it)."""

    def carried(e: Event | EngineEvent) -> bool:
        return isinstance(e, StatusChanged) and e.report.get(key) == value

    return carried


def faults_told(bench: Bench) -> list[dict[str, Any]]:
    return [e.fault for e in bench.recorder.events if isinstance(e, FaultChanged)]


def job_state(bench: Bench, job_id: int) -> str:
    """The job's state as the last `job` event told it."""
    told = [
        e.job["state"]
        for e in bench.recorder.events
        if isinstance(e, JobChanged) and e.job["id"] == job_id
    ]
    return told[-1]


# -- which state admits a job --------------------------------------------------------


async def test_a_move_a_client_sent_makes_the_machine_busy_and_a_job_waits_for_it(
    bench: Bench,
) -> None:
    """The operator sends a long move by hand: while the board runs it the machine shows
    `busy` and refuses job.start (1003), so a job never starts under a moving tool."""
    bench.write("part.gcode", "G0 X1\n")
    await bench.machine.send("G1 X40 F30")  # answered as queued; the board runs it
    await bench.recorder.wait_for(reported("stat", 5))  # a report says it runs
    assert bench.machine.supervisor.state is Sup.BUSY
    with pytest.raises(Refused) as err:
        await bench.machine.start_make("part.gcode")
    assert err.value.code == 1003
    assert await bench.store.list_jobs() == []
    bench.machine.jog_stop()
    await bench.supervisor(Sup.IDLE)


async def test_a_line_the_board_has_not_answered_keeps_the_machine_busy(tmp_path: Path) -> None:
    """A line the host wrote and the board has not yet answered (a board slow to read) is
    work in progress: the machine shows `busy`, not `idle`, though every report still says
    the board rests, and job.start is 1003 until the answer comes."""
    # A key whose change the board reports, at a reading that raises no fault.
    signals = {"coolant_temp_high": {"key": "ain2", "above": 1000.0}}
    async with bench_for(tmp_path, signals=signals) as bench:
        bench.write("part.gcode", "G0 X1\n")
        bench.machine.console = True  # the recorder reads the traffic
        bench.sim.stop_reading()
        sent = asyncio.create_task(bench.machine.send("G0 X5"))
        await bench.recorder.wait_for(
            lambda e: isinstance(e, Console) and e.direction == "tx" and "G0 X5" in e.text
        )
        bench.sim.set_analog(2, 20.0)  # a report comes: the board still rests (STOP)
        await bench.recorder.wait_for(reported("ain2", 20.0))
        assert bench.machine.engine.model.state is not None
        assert bench.machine.engine.model.state.is_resting
        assert bench.machine.supervisor.state is Sup.BUSY
        with pytest.raises(Refused) as err:
            await bench.machine.start_make("part.gcode")
        assert err.value.code == 1003
        bench.sim.resume_reading()
        assert (await sent).status == 0


# -- signal faults on the machine ------------------------------------------------------


async def test_an_estop_wired_to_an_input_stops_a_running_job(tmp_path: Path) -> None:
    """An e-stop button read through an input (`[machines.signals] estop`), not the
    board's own e-stop: pressing it mid-job raises `estop` and the job ends `failed` with
    1007, as the board's SHUTDOWN would."""
    signals = {"estop": {"key": "in4", "equals": 1}}
    async with bench_for(tmp_path, signals=signals) as bench:
        bench.write("long.gcode", LONG)
        job = await bench.machine.start_make("long.gcode")
        await bench.sim.wait_state(S.RUN)
        bench.sim.set_input(4, 1)
        await bench.recorder.wait_for(fault_became("estop", True))
        row = await bench.job_ended(job.id)
        assert row.state == "failed" and row.error is not None
        assert row.error.code == 1007 and "estop" in row.error.message
        assert row.lines_acked < row.lines_total


async def test_the_coolant_temperature_fault_holds_until_a_degree_below_its_limit(
    tmp_path: Path,
) -> None:
    """`hysteresis` on the machine, not only in the signal's own rule: a reading that
    dips just under the limit (29.5 for 30 with 1.0) keeps the fault, and a job stays
    refused with 1007; only at 28.9 does it clear."""
    signals = {"coolant_temp_high": {"key": "ain2", "above": 30.0, "hysteresis": 1.0}}
    async with bench_for(tmp_path, signals=signals) as bench:
        bench.write("part.gcode", "G0 X1\n")
        bench.sim.set_analog(2, 31.0)
        await bench.recorder.wait_for(fault_became("water_temp", True))
        bench.sim.set_analog(2, 29.5)
        await bench.recorder.wait_for(reported("ain2", 29.5))
        assert bench.machine.faults.get("water_temp").active
        with pytest.raises(FaultActive) as err:
            await bench.machine.start_make("part.gcode")
        assert err.value.data == ["water_temp"]
        bench.sim.set_analog(2, 28.9)
        await bench.recorder.wait_for(fault_became("water_temp", False))


async def test_a_signal_fault_says_what_it_means_without_a_reading(tmp_path: Path) -> None:
    """A flow *switch* (an input that opens when flow stops) has no reading: the
    operator reads "coolant flow stopped or below minimum", not a value the daemon never
    had ("coolant flow low (None)"), nor the switch's 0."""
    signals = {"coolant_flow_low": {"key": "in6", "equals": 0}}
    async with bench_for(tmp_path, signals=signals) as bench:
        bench.sim.set_input(6, 1)
        bench.sim.set_input(6, 0)
        event = await bench.recorder.wait_for(fault_became("water_flow", True))
        assert isinstance(event, FaultChanged)
        assert event.fault["message"] == "coolant flow stopped or below minimum"
        assert event.fault["value"] is None
        assert bench.machine.snapshot()["faults"][0]["message"] == event.fault["message"]


async def test_a_coolant_fault_keeps_the_reading_that_raised_it(tmp_path: Path) -> None:
    """A flow meter's fault says the flow that raised it ("coolant flow low (0.2)"), and
    keeps it while the reading moves below the limit: a change told at every report
    would only repeat the fault."""
    signals = {"coolant_flow_low": {"key": "ain1", "below": 1.0}}
    async with bench_for(tmp_path, signals=signals) as bench:
        bench.sim.set_analog(1, 2.0)  # flowing (the simulated meter starts at 0)
        await bench.recorder.wait_for(fault_became("water_flow", False))
        bench.sim.set_analog(1, 0.2)
        raised = fault_became("water_flow", True)
        event = await bench.recorder.wait_for(lambda e: raised(e) and e.fault["value"] != 0)
        assert isinstance(event, FaultChanged)
        assert (event.fault["value"], event.fault["message"]) == (0.2, "coolant flow low (0.2)")
        told = len(bench.recorder.events)
        bench.sim.set_analog(1, 0.3)
        await bench.recorder.wait_for(  # the machine has read the new flow
            lambda e: isinstance(e, StatusChanged) and e.report.get("ain1") == 0.3
        )
        bench.sim.set_analog(1, 2.0)  # flowing again
        cleared = fault_became("water_flow", False)
        events = bench.recorder.events
        await bench.recorder.wait_for(
            lambda e: cleared(e) and any(e is later for later in events[told:])
        )
        changes = [
            e
            for e in bench.recorder.events[told:]
            if isinstance(e, FaultChanged) and e.fault["id"] == "water_flow"
        ]
        assert [c.fault["active"] for c in changes] == [False], changes


# -- software faults: when they began, what clears them ------------------------------------


async def test_a_fault_the_daemon_detected_says_when_it_began(bench: Bench) -> None:
    """Line noise is a `serial` fault whose `since` is the moment it came, as for a
    signal fault: the operator matches it with what happened on the shop floor."""
    before = time.time()
    bench.sim.inject_garbage(b"\xff\xfe\x01 noise\n")
    event = await bench.recorder.wait_for(fault_became("serial", True))
    assert isinstance(event, FaultChanged)
    since = datetime.fromisoformat(event.fault["since"]).timestamp()
    assert before - 1 <= since <= time.time() + 1


async def test_a_reset_that_never_reached_the_board_clears_no_fault(bench: Bench) -> None:
    """machine.reset on a machine that is not connected fails (1002) and leaves the
    faults a reset would clear: the board was not reset, so nothing it did is forgiven
    and a job is still refused (1007)."""
    bench.write("part.gcode", "G0 X1\n")
    bench.sim.inject_garbage(b"\xff\xfe\x01 noise\n")
    await bench.recorder.wait_for(fault_became("serial", True))
    await bench.machine.disconnect()
    told = len(faults_told(bench))
    with pytest.raises(NotConnected):
        await bench.machine.reset()
    assert bench.machine.faults.get("serial").active
    assert bench.machine.snapshot()["indicator"] == "alert"
    assert len(faults_told(bench)) == told  # nobody was told it cleared


async def test_clearing_a_fault_that_is_not_active_tells_nobody(bench: Bench) -> None:
    """fault.clear on an inactive fault answers it as it is and publishes nothing: a
    dashboard does not log a `lexical` fault change that never happened."""
    before = faults_told(bench)
    fault = bench.machine.clear_fault("lexical")
    assert not fault.active
    assert faults_told(bench) == before


# -- what a client is told as the supervisor moves ----------------------------------------


async def test_a_disconnect_asked_for_and_a_link_lost_are_told_apart(bench: Bench) -> None:
    """The supervisor topic says `disconnect` when the operator asked, `disconnected` when
    the link was lost: also after the machine was disconnected once and connected again."""
    await bench.machine.disconnect()
    await bench.supervisor(Sup.DISCONNECTED)
    assert bench.transitions()[-1] == ("idle", "disconnect", "disconnected")
    await bench.machine.connect()
    await bench.supervisor(Sup.IDLE)
    await bench.sim.unplug()
    await bench.supervisor(Sup.DISCONNECTED)
    assert bench.transitions()[-1] == ("idle", "disconnected", "disconnected")


async def test_whoever_is_told_of_a_supervisor_change_reads_the_new_state(
    bench: Bench,
) -> None:
    """A client told the supervisor moved, and the daemon's own status line (systemd's
    STATUS=), read the machine as it is now, not one state behind."""
    seen: list[tuple[str, str]] = []

    def told(event: Event) -> None:
        if isinstance(event, SupervisorChanged):
            seen.append((event.target, bench.machine.snapshot()["supervisor"]))

    bench.machine.hub.subscribe(told)
    await bench.machine.disconnect()
    await bench.machine.connect()
    await bench.supervisor(Sup.IDLE)
    assert seen[:3] == [("disconnected", "disconnected"), ("busy", "busy"), ("idle", "idle")]
    assert all(target == shown for target, shown in seen)


async def test_a_grbl_reset_brings_the_machine_back_without_a_failure_logged(
    tmp_path: Path,
) -> None:
    """grbl resets in place and re-syncs on the same link, which comes up again while the
    machine is connected: the machine stays connected and idle, and the journal shows no
    traceback of the machine failing on the engine's event at each reset."""
    async with grbl_bench(tmp_path) as bench:
        with capture_logs() as logs:
            await bench.machine.reset()
            await bench.supervisor(Sup.IDLE)
        failed = [entry for entry in logs if entry["log_level"] in ("error", "critical")]
        assert failed == []
        assert ("disconnected", "connect", "busy") not in bench.transitions()[2:]


async def test_a_job_cut_off_by_an_unplug_ends_without_a_failure_logged(bench: Bench) -> None:
    """The cable is pulled mid-job: the job ends `interrupted` while the machine is
    already `disconnected`, and the journal shows no traceback of the machine trying to
    leave an operation it had already left."""
    bench.write("long.gcode", LONG)
    with capture_logs() as logs:
        job = await bench.machine.start_make("long.gcode")
        await bench.sim.wait_state(S.RUN)
        await bench.sim.unplug()
        assert (await bench.job_ended(job.id)).state == "interrupted"
        await bench.machine.jobs.followed(timeout=5)
    assert bench.machine.supervisor.state is Sup.DISCONNECTED
    failed = [entry for entry in logs if entry["log_level"] in ("error", "critical")]
    assert failed == []


# -- an operation's move that ends in a lockout ---------------------------------------------


async def test_a_go_to_zero_stopped_by_a_limit_switch_fails_at_once(tmp_path: Path) -> None:
    """A limit switch trips on the way to work zero: the operation answers at once that
    its move ended in ALARM, rather than "done" or nothing for the ten minutes it would
    wait for the board to rest at zero."""
    slow = dataclasses.replace(FAST, rapid_rate=300.0)  # G0 X100 is 0.4 s on the board
    async with bench_for(tmp_path, sim_config=slow) as bench:
        engine = bench.machine.engine
        await bench.machine.send("G0 X100")
        async with asyncio.timeout(5):
            await engine.wait_for(
                lambda: (
                    engine.model.position.get("x") == 100.0
                    and bench.machine.supervisor.state is Sup.IDLE
                )
            )
        going = asyncio.create_task(operations.goto_zero(bench.machine, ["x"]))
        await bench.sim.wait_state(S.RUN)
        bench.sim.limit_switch("x")
        with pytest.raises(ControllerError, match="ended in ALARM"):
            async with asyncio.timeout(10):  # a bound for a hang, not a timing check
                await going


# -- the pause gates ----------------------------------------------------------------------


async def test_a_feedhold_during_a_jog_holds_the_board_and_pauses_no_job(bench: Bench) -> None:
    """Only a make job pauses (api.md): `machine.feedhold` during a jog sends `!` and the
    jog stays a running operation, which `machine.jog_stop` then ends."""
    job = await bench.machine.jog({"x": 40.0}, 30)  # 1.6 s on FAST's board
    await bench.sim.wait_state(S.RUN)
    bench.machine.feedhold()
    await bench.sim.wait_state(S.HOLD)
    assert bench.machine.supervisor.state is Sup.OPERATION
    assert job_state(bench, job.id) == "running"
    bench.machine.jog_stop()
    assert (await bench.job_ended(job.id)).state != "paused"
    await bench.supervisor(Sup.IDLE)


async def test_a_second_feedhold_on_a_paused_job_only_holds_again(bench: Bench) -> None:
    """An operator who presses hold twice is not answered 1003: the second `!` goes to
    the board and the job stays paused, to be resumed as before."""
    bench.write("long.gcode", LONG)
    job = await bench.machine.start_make("long.gcode")
    await bench.sim.wait_state(S.RUN)
    bench.machine.feedhold()
    assert bench.machine.supervisor.state is Sup.PAUSED
    bench.machine.feedhold()
    assert bench.machine.supervisor.state is Sup.PAUSED
    assert job_state(bench, job.id) == "paused"
    bench.machine.resume()
    assert bench.machine.supervisor.state is Sup.OPERATION
    await bench.machine.cancel()


async def test_a_cycle_start_during_a_running_job_only_sends_it(bench: Bench) -> None:
    """`machine.cycle_start` while the job runs is the board's `~`, not a resume of a job
    that is not paused: no 1003, and the job runs on."""
    bench.write("long.gcode", LONG)
    job = await bench.machine.start_make("long.gcode")
    await bench.sim.wait_state(S.RUN)
    bench.machine.cycle_start()
    assert bench.machine.supervisor.state is Sup.OPERATION
    assert job_state(bench, job.id) == "running"
    await bench.machine.cancel()
