"""Client actions and board events in any order; the rules of "What must never happen" hold.

A hypothesis state machine drives the real machine layer (Machine, Engine,
JobStore on SQLite) over the simulated g2core on a real pty, through the
API's own method table, as a client would. Rules are client requests
(start, pause, resume, cancel, send, settings, clear, reset, feedhold, jog,
disconnect ...), board events (alarm, e-stop, panic, interlock, unplug,
garbage, slow acks, a board that stops reading) and the passing of time
(loop iterations, a short sleep, the next event of a kind, a job's end).

A request either is waited for (bounded) or stays in flight while later
rules run: that is how a `machine.send` comes to wait across a resume, or a
pause to land while `job.start` writes its row. The loop runs only inside a
rule, so between two rules nothing moves: each interleaving a rule sequence
describes is the one that runs.

Every check is made on recorded facts (observer.py reads the rules from the
machine's events; the board's own log of what it read; the job rows), never
on how long something took. A violation says at which step it was seen:
step N is the N-th rule of the printed example (0: setting up).

HOSTD_STATEFUL_PROFILE selects the budget: unset, a bounded derandomised
set for `make test`; `shrink`, the same set with a failure shrunk (minutes);
`soak`, many longer random examples for `make soak`.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import sys
import tempfile
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import pytest
from hypothesis import HealthCheck, Phase, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule

from hostd.api.methods import Api, build_methods
from hostd.api.rpc import Methods, dispatch
from hostd.config import parse_config
from hostd.daemon import Daemon
from hostd.machine.events import JobChanged, StatusChanged, SupervisorChanged
from hostd.machine.jobstore import Job, JobStore
from hostd.machine.machine import Machine
from hostd.protocol.errors import NotConnected
from hostd.protocol.states import MachineState
from hostd.sim import SimController
from tests.machine.conftest import FAST, machine_config
from tests.stateful.observer import (
    FINAL,
    REALTIME,
    Observer,
    client_line,
    job_file,
    job_line,
)

T = TypeVar("T")

_COMMON = settings(
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)
_BOUNDED = settings(_COMMON, max_examples=20, stateful_step_count=25, derandomize=True)
PROFILES = {
    # `make test`: the same examples on every run, well under a minute on two cores. No
    # shrinking (each example runs in real time): a failure shows its whole run.
    "default": settings(_BOUNDED, phases=[Phase.explicit, Phase.generate]),
    # The same examples, and a failure shrunk to the fewest steps that still break the rule.
    "shrink": settings(_BOUNDED, phases=[Phase.explicit, Phase.generate, Phase.shrink]),
    # `make soak`: new random examples every run, longer ones, shrunk; a failure prints
    # the blob that replays it (@reproduce_failure).
    "soak": settings(_COMMON, max_examples=300, stateful_step_count=40, print_blob=True),
}
PROFILE = PROFILES[os.environ.get("HOSTD_STATEFUL_PROFILE", "default")]

MACHINE = "m1"
WAIT = 3.0  # the longest a rule waits for a request it waits for
SEND_TIMEOUT = 1.0  # machine.send's own timeout
SETTLE = 15.0  # at the end, the longest to wait for requests still in flight
STEP_LIMIT = 30.0  # no step runs the loop longer: a hang is reported, not waited out
API_CODES = frozenset({-32700, -32600, -32601, -32602, 204, 205, 206, *range(1001, 1009)})
RESULT_STATES = {"job.pause": {"paused"}, "job.resume": {"running"}, "job.cancel": FINAL}
SETTING_VALUES = [{"xvm": 12000}, {"xvm": "fast"}, {"zzz": 1}, {"boot": 1}]
BOARD_EVENTS: dict[str, Callable[[SimController], Awaitable[None] | None]] = {
    "limit switch": lambda sim: sim.limit_switch("x"),  # ALARM
    "e-stop pressed": lambda sim: sim.estop(True),  # SHUTDOWN
    "e-stop released": lambda sim: sim.estop(False),
    "panic": lambda sim: sim.panic(),
    "interlock open": lambda sim: sim.interlock(True),
    "interlock closed": lambda sim: sim.interlock(False),
    "unplugged": lambda sim: sim.unplug(),
    "plugged in": lambda sim: sim.replug(),
    "bytes that are not text": lambda sim: sim.inject_garbage(b"\xfe\xff garbage\n"),
    "a line that is not JSON": lambda sim: sim.inject_garbage(b"{bogus: \n"),
    "slow acks": lambda sim: sim.set_ack_delay(0.3),
    "prompt acks": lambda sim: sim.set_ack_delay(0.0),
    "stops reading": lambda sim: sim.stop_reading(),
    "reads again": lambda sim: sim.resume_reading(),
}
ADVANCES = [
    ("ticks", 1),
    ("ticks", 10),
    ("sleep", 0.01),
    ("sleep", 0.1),
    ("event", "status"),
    ("event", "supervisor"),
    ("event", "job"),
    ("event", "rest"),  # the host reads that the board stopped
]


@dataclass
class Request:
    method: str
    params: dict[str, Any]
    task: asyncio.Task[dict[str, Any]]
    link_up: bool  # when it was made
    judged: bool = False

    def __str__(self) -> str:
        return f"{self.method} {json.dumps(self.params)}"


class Rig:
    """A Machine over a simulated board on a pty, its job store, and the API's method table."""

    def __init__(self, root: Path) -> None:
        path = str(root / "ttyG2")
        config = parse_config(
            {
                "daemon": {"socket": str(root / "hostd.sock"), "state_dir": str(root / "state")},
                "machines": [{"id": MACHINE, "data_port": path}],
            }
        )
        self.daemon = Daemon(config)
        self.daemon.jobs_dir.mkdir(parents=True)
        self.store = JobStore(root / "jobs.db")
        self.daemon.store = self.store
        self.sim = SimController(path, config=FAST)
        self.machine = Machine(machine_config(path, id=MACHINE), self.store, self.daemon.jobs_dir)
        self.daemon.machines[MACHINE] = self.machine
        self.methods: Methods = build_methods(Api(self.daemon))
        self.machine.engine.console = True  # the observer reads the traffic
        self.observer = Observer(self.machine, self.machine.config.window)
        self.changed = asyncio.Event()
        self.serving: asyncio.Task[None] | None = None

    async def open(self) -> None:
        self.machine.hub.subscribe(self.observer)
        self.machine.hub.subscribe(lambda _: self.changed.set())
        await self.sim.start()
        self.serving = asyncio.create_task(self.machine.serve())
        for attempt in range(3):
            try:
                await self.machine.connect()
                break
            except NotConnected:
                # On a loaded machine the simulator's fallback banner can beat the
                # host's flush: two banners, and the host rightly calls it a restart.
                if attempt == 2:
                    raise
        await self.until(lambda: self.machine.supervisor.state.value == "idle", 5.0)

    async def until(self, predicate: Callable[[], bool], timeout: float) -> bool:
        """Whether `predicate` became true within `timeout`, re-checked after every event."""
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout):
                while not predicate():
                    self.changed.clear()
                    await self.changed.wait()
                return True
        return False

    async def next_event(self, wanted: Callable[[object], bool], timeout: float) -> None:
        events: list[object] = []
        unsubscribe = self.machine.hub.subscribe(events.append)
        try:
            await self.until(lambda: any(wanted(e) for e in events), timeout)
        finally:
            unsubscribe()

    async def call(self, method: str, params: dict[str, Any]) -> dict[str, Any]:
        """One JSON-RPC request through the API's method table, as a client sends it."""
        if method == "machine.send":
            self.observer.admit(params["line"])  # the step in which the engine admits it
        request = {"jsonrpc": "2.0", "id": 1, "method": method, "params": params}
        answer = await dispatch(json.dumps(request).encode(), self.methods, None)
        assert answer is not None
        result: dict[str, Any] = json.loads(answer)
        return result

    async def close(self) -> None:
        if self.serving is not None:
            self.serving.cancel()
            await asyncio.gather(self.serving, return_exceptions=True)
        try:
            await self.sim.close()
        finally:
            self.store.close()


class WhatMustNeverHappen(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.requests: list[Request] = []
        self.files = 0
        self.sends = 0
        self.settings_sets = 0
        self._rows_reported = 0
        self.unplugged = False
        self._read_upto = 0  # how much of the board's log has been matched
        self._tx_at = {"line": 0, "realtime": 0}
        self._tmp = tempfile.TemporaryDirectory(prefix="hostd-stateful-")
        self.loop = asyncio.new_event_loop()
        self.rig = Rig(Path(self._tmp.name))
        try:
            self.run(self.rig.open())
        except BaseException:
            self._close()
            raise

    def run(self, coro: Awaitable[T]) -> T:
        """Run the loop until `coro` is done: the only time anything moves."""
        return self.loop.run_until_complete(asyncio.wait_for(coro, STEP_LIMIT))

    # -- client requests -----------------------------------------------------

    def request(self, method: str, wait: bool = True, **params: Any) -> None:
        params = {"machine": MACHINE, **params}
        task = self.loop.create_task(self.rig.call(method, params))
        self.requests.append(Request(method, params, task, self.rig.machine.engine.ready))
        self.run(asyncio.wait({task}, timeout=WAIT if wait else 0))

    @rule(length=st.sampled_from([3, 40, 150]), wait=st.booleans())
    def start(self, length: int, wait: bool) -> None:
        self.files += 1
        text = "".join(f"{job_line(self.files, i)}\n" for i in range(1, length + 1))
        (self.rig.daemon.jobs_dir / job_file(self.files)).write_text(text)
        self.request("job.start", wait, file=job_file(self.files))

    @rule()
    def pause(self) -> None:
        self.request("job.pause")

    @rule()
    def resume(self) -> None:
        self.request("job.resume")

    @rule(wait=st.booleans())
    def cancel(self, wait: bool) -> None:
        self.request("job.cancel", wait)

    @rule()
    def feedhold(self) -> None:
        self.request("machine.feedhold")

    @rule()
    def cycle_start(self) -> None:
        self.request("machine.cycle_start")

    @rule(query=st.booleans(), wait=st.booleans())
    def send(self, query: bool, wait: bool) -> None:
        self.sends += 1
        line = '{"xvm":null}' if query else client_line(self.sends)
        self.request("machine.send", wait, line=line, timeout=SEND_TIMEOUT)

    @rule(wait=st.booleans())
    def settings_get(self, wait: bool) -> None:
        self.request("settings.get", wait, keys=["xvm"])

    @rule(values=st.sampled_from(SETTING_VALUES), wait=st.booleans())
    def settings_set(self, values: dict[str, Any], wait: bool) -> None:
        self.settings_sets += 1
        self.request("settings.set", wait, values=values)

    @rule(wait=st.booleans())
    def clear(self, wait: bool) -> None:
        self.request("machine.clear", wait)

    @rule(wait=st.booleans())
    def reset(self, wait: bool) -> None:
        self.request("machine.reset", wait)

    @rule(wait=st.booleans())
    def jog(self, wait: bool) -> None:
        self.request("machine.jog", wait, axes={"x": 1.0}, feed=600)

    @rule()
    def disconnect(self) -> None:
        self.request("machine.disconnect")

    @rule()
    def connect(self) -> None:
        self.request("machine.connect")

    @rule(fault=st.sampled_from(["serial", "lexical", "underflow"]))
    def clear_fault(self, fault: str) -> None:
        self.request("fault.clear", fault=fault)

    # -- board events ----------------------------------------------------------

    @rule(event=st.sampled_from(sorted(BOARD_EVENTS)))
    def board(self, event: str) -> None:
        """One thing the board (or its cable) does, then one loop iteration to read it."""
        if event == "unplugged":
            self.unplugged = True
        elif event == "plugged in":
            self.unplugged = False
        happened = BOARD_EVENTS[event](self.rig.sim)
        if happened is not None:
            self.run(happened)
        self.run(asyncio.sleep(0))

    # -- time ------------------------------------------------------------------

    @rule(how=st.sampled_from(ADVANCES))
    def advance(self, how: tuple[str, Any]) -> None:
        kind, arg = how
        if kind == "ticks":
            self.run(_ticks(arg))
        elif kind == "sleep":
            self.run(asyncio.sleep(arg))
        else:
            self.run(self.rig.next_event(_EVENTS[arg], 0.5))

    @rule()
    def until_the_job_ends(self) -> None:
        """Let the operation that runs now reach its end (bounded: it may be paused)."""
        observer = self.rig.observer
        job = observer.operation_job
        if job is not None:
            self.run(self.rig.until(lambda: observer.job_state(job) in FINAL, 1.5))

    # -- the rules that must hold ------------------------------------------------
    #
    # Facts are judged after every step (and as each event is published), but
    # reported at the end, from `teardown`: a run that stopped at the step where
    # a timing-dependent violation showed would make hypothesis see a different
    # number of steps for the same choices on a replay. Each rule asserts on its
    # own line, so that each broken rule is reported as its own bug.

    @invariant()
    def facts_are_judged_after_every_step(self) -> None:
        self._collect()
        self.rig.observer.step += 1

    def no_job_line_is_written_while_paused(self) -> None:
        found = self._violations("paused")
        assert not found, _report("paused", found)

    def job_lines_go_once_in_order_within_their_operation(self) -> None:
        found = self._violations("stream")
        assert not found, _report("stream", found)

    def nothing_is_written_to_a_locked_out_board(self) -> None:
        found = self._violations("lockout")
        assert not found, _report("lockout", found)

    def the_window_is_never_exceeded(self) -> None:
        found = self._violations("window")
        assert not found, _report("window", found)

    def lines_acked_never_decreases(self) -> None:
        found = self._violations("acked")
        assert not found, _report("acked", found)

    def a_jobs_end_state_is_final(self) -> None:
        found = self._violations("final")
        assert not found, _report("final", found)

    def completed_means_every_line_was_answered(self) -> None:
        found = self._violations("completed")
        assert not found, _report("completed", found)

    def the_supervisor_agrees_with_the_job(self) -> None:
        found = self._violations("supervisor")
        assert not found, _report("supervisor", found)

    def client_lines_never_run_inside_an_operation_or_a_lockout(self) -> None:
        found = self._violations("client")
        assert not found, _report("client", found)

    def in_hold_lines_run_only_in_the_hold_they_were_admitted_in(self) -> None:
        found = self._violations("in-hold")
        assert not found, _report("in-hold", found)

    def reading_settings_works_in_every_state_and_makes_no_row(self) -> None:
        found = self._violations("query")
        assert not found, _report("query", found)

    def every_request_is_answered_as_the_api_says(self) -> None:
        found = self._violations("request")
        assert not found, _report("request", found)

    def the_daemon_runs_on_and_the_board_read_only_what_it_wrote(self) -> None:
        found = self._violations("daemon")
        assert not found, _report("daemon", found)

    def rows_agree_with_what_was_published(self) -> None:
        found = self._violations("rows")
        assert not found, _report("rows", found)

    def _violations(self, rule: str) -> list[str]:
        return self.rig.observer.violations.get(rule, [])

    def _check_all(self) -> None:
        """In the order a reader wants them: the machine's safety first."""
        self.no_job_line_is_written_while_paused()
        self.nothing_is_written_to_a_locked_out_board()
        self.in_hold_lines_run_only_in_the_hold_they_were_admitted_in()
        self.client_lines_never_run_inside_an_operation_or_a_lockout()
        self.job_lines_go_once_in_order_within_their_operation()
        self.the_window_is_never_exceeded()
        self.a_jobs_end_state_is_final()
        self.completed_means_every_line_was_answered()
        self.lines_acked_never_decreases()
        self.the_supervisor_agrees_with_the_job()
        self.reading_settings_works_in_every_state_and_makes_no_row()
        self.every_request_is_answered_as_the_api_says()
        self.the_daemon_runs_on_and_the_board_read_only_what_it_wrote()
        self.rows_agree_with_what_was_published()

    # -- facts gathered before each check --------------------------------------

    def _collect(self) -> None:
        observer = self.rig.observer
        for request in self.requests:
            if request.task.done() and not request.judged:
                request.judged = True
                self._judge(request)
        rows = len(observer.settings_rows)
        if rows > max(self.settings_sets, self._rows_reported):
            self._rows_reported = rows
            observer.fail(
                "query",
                f"{rows} settings rows for {self.settings_sets} settings.set: "
                "settings.get made a job row",
            )
        self._board_read()
        serving = self.rig.serving
        if serving is not None and serving.done():
            observer.fail("daemon", f"the machine stopped serving: {serving!r}")
        self._supervisor_at_rest()

    def _judge(self, request: Request) -> None:
        fail = self.rig.observer.fail
        if request.task.cancelled():
            return
        exc = request.task.exception()
        if exc is not None:
            fail("request", f"{request} raised {exc!r}")
            return
        answer = request.task.result()
        error = answer.get("error")
        if error is not None:
            code = error["code"]
            if code not in API_CODES:
                fail("request", f"{request} answered {error}")
            refused = code in (204, 205, 206, 1003)
            if request.method == "settings.get" and request.link_up and refused:
                fail("query", f"{request} refused with the link up: {error}")
            return
        expected = RESULT_STATES.get(request.method)
        state = answer["result"].get("state") if expected else None
        if expected and state not in expected:
            fail("request", f"{request} answered a job that is {state}: {answer['result']}")

    def _board_read(self) -> None:
        """The board read only lines the host reported writing, in the order written."""
        received = self.rig.sim.received
        for entry in received[self._read_upto :]:
            kind = "realtime" if entry.kind == "realtime" else "line"
            text = entry.data.decode("utf-8", "backslashreplace")
            if not self._match_written(kind, text):
                self.rig.observer.fail(
                    "daemon", f"the board read {text!r} ({kind}), not written there by the host"
                )
        self._read_upto = len(received)

    def _match_written(self, kind: str, text: str) -> bool:
        tx = self.rig.observer.tx
        at = self._tx_at[kind]
        while at < len(tx):
            item = tx[at]
            at += 1
            # `%` is a realtime byte to the host; a board that has no hold reads it as a line.
            same_kind = (item in REALTIME) == (kind == "realtime") or item == "%"
            if same_kind and item == text:
                self._tx_at[kind] = at
                return True
        return False

    def _supervisor_at_rest(self) -> None:
        """Between two rules: a job shown live is the supervisor's operation."""
        supervisor = self.rig.machine.supervisor.state.value
        job = self.rig.machine.current_job()
        if job is None:
            return
        if job.state in ("running", "paused") and supervisor == "idle":
            self.rig.observer.fail("supervisor", f"job {job.id} is {job.state} on an idle machine")
        if job.state == "paused" and supervisor not in ("paused", "disconnected"):
            self.rig.observer.fail(
                "supervisor", f"job {job.id} is paused while the supervisor is {supervisor}"
            )

    # -- the end ---------------------------------------------------------------

    def teardown(self) -> None:
        failing = sys.exc_info()[1] is not None  # a step raised: report that, not more
        try:
            if not failing and not self.rig.observer.violations:  # else it fails anyway
                self.run(self._settle())
                self.run(self._check_rows())
                self._collect()
        finally:
            self._close()
        if not failing:
            self._check_all()

    async def _settle(self) -> None:
        """Let the board answer again and every request in flight finish."""
        sim = self.rig.sim
        sim.resume_reading()
        sim.set_ack_delay(0)
        if self.unplugged:
            await sim.replug()
        pending = [r.task for r in self.requests if not r.task.done()]
        if pending:
            await asyncio.wait(pending, timeout=SETTLE)

    async def _check_rows(self) -> None:
        observer = self.rig.observer
        machine = self.rig.machine
        for row in await self.rig.store.list_jobs(MACHINE, limit=10_000):
            if row.state not in FINAL and not _live(machine, row.id):
                row = await self._row_settled(row.id)
                if row.state not in FINAL and not _live(machine, row.id):
                    observer.fail("rows", f"job {row.id} left {row.state} with no operation")
            if (row.ended_at is not None) != (row.state in FINAL):
                observer.fail("rows", f"job {row.id} is {row.state} with ended_at {row.ended_at}")
            told = observer.job_state(row.id)
            if told in FINAL and row.state != told:
                observer.fail("rows", f"job {row.id} was published {told}, its row is {row.state}")
            if row.state == "completed" and row.lines_acked != row.lines_total:
                observer.fail(
                    "completed",
                    f"row {row.id} completed with {row.lines_acked} of {row.lines_total} answered",
                )

    async def _row_settled(self, job_id: int) -> Job:
        """The row once its end is on disk (the runner may still be writing it), or as it is."""
        machine = self.rig.machine
        deadline = self.loop.time() + 2.0
        while True:
            row = await self.rig.store.get(job_id)
            assert row is not None
            if row.state in FINAL or _live(machine, job_id) or self.loop.time() > deadline:
                return row
            await asyncio.sleep(0.02)

    def _close(self) -> None:
        try:
            for request in self.requests:
                request.task.cancel()
            if self.requests:
                tasks = [r.task for r in self.requests]
                self.run(asyncio.gather(*tasks, return_exceptions=True))
            self.run(self.rig.close())
            self.run(self.loop.shutdown_asyncgens())
            self.run(self.loop.shutdown_default_executor())
        finally:
            self.loop.close()
            self._tmp.cleanup()


def _report(rule: str, found: list[str]) -> str:
    shown = "\n  ".join(found[:5])
    more = f"\n  ... and {len(found) - 5} more" if len(found) > 5 else ""
    return f"{rule}: {len(found)} violation(s)\n  {shown}{more}"


def _live(machine: Machine, job_id: int) -> bool:
    job = machine.current_job()
    supervisor = machine.supervisor.state.value
    return job is not None and job.id == job_id and supervisor in ("operation", "paused")


async def _ticks(n: int) -> None:
    for _ in range(n):
        await asyncio.sleep(0)


def _is_rest(event: object) -> bool:
    return isinstance(event, StatusChanged) and event.report.get("stat") in (
        MachineState.PROGRAM_STOP,
        MachineState.PROGRAM_END,
    )


_EVENTS: dict[str, Callable[[object], bool]] = {
    "status": lambda e: isinstance(e, StatusChanged),
    "supervisor": lambda e: isinstance(e, SupervisorChanged),
    "job": lambda e: isinstance(e, JobChanged),
    "rest": _is_rest,
}

WhatMustNeverHappen.TestCase.settings = PROFILE
# Twenty runs of up to 25 steps on a board that moves in real time: about 25 s alone,
# past the suite's 60 s per test when six workers share two cores. Each step has its
# own bound (STEP_LIMIT); this one is only the whole run's. The `shrink` and `soak`
# profiles run for many minutes by design: the mark would outrank `--timeout=0`
# (make soak) and end them as a "failure" at 240 s, so they get none.
WHOLE_RUN_LIMIT = 240 if PROFILE is PROFILES["default"] else 0  # 0: no limit
TestWhatMustNeverHappen = pytest.mark.timeout(WHOLE_RUN_LIMIT)(WhatMustNeverHappen.TestCase)
