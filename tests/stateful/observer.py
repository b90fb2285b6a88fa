"""The rules of "What must never happen", judged from what the machine published.

The observer listens on the machine's hub. The console topic is every line
and realtime byte the engine wrote and every line it read, in the order it
did so; status reports say what the host knew of the board; supervisor
transitions and job objects say what clients were told. Each event is
judged when it is published, against the facts before it, and with the
supervisor's state read at that very moment (publishing is synchronous), so
no check depends on how long anything took. A broken rule is written down
under its name; the test asserts per name, so that each rule that breaks is
reported as its own bug.

Lines are recognised by their text: every job file and every client line
of the test is unique (see `job_line` and `client_line`).
"""

from __future__ import annotations

import json
import re
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

from hostd.machine.events import (
    Console,
    Event,
    FaultChanged,
    JobChanged,
    LinkChanged,
    StatusChanged,
    SupervisorChanged,
)
from hostd.machine.machine import Machine
from hostd.protocol.states import MachineState

FINAL = frozenset({"completed", "failed", "cancelled", "interrupted"})
LOCKOUT = frozenset({MachineState.ALARM, MachineState.SHUTDOWN, MachineState.PANIC})
HOLD_ENDS = frozenset("~%\x04\x18")  # cycle start, flush, kill, reset
FORGETS = frozenset("%\x04\x18")  # after these the board may drop lines unanswered
REALTIME = frozenset("!~%\x04\x18\x05")
# The supervisor states a live job may be published in (a lost link ends it a moment later).
LIVE = frozenset({"operation", "paused", "disconnected"})

_JOB_LINE = re.compile(r"G1 X\d+ Y(\d+)\.(\d{3}) F3000")
_CLIENT_LINE = re.compile(r"G0 Z0\.\d{3}")


def job_line(file: int, line: int) -> str:
    """Line `line` (1-based) of job file `file`: its number is in the Y word."""
    return f"G1 X{(line % 2) * 4 + 1} Y{file}.{line:03d} F3000"


def job_file(file: int) -> str:
    return f"job{file}.gcode"


def client_line(n: int) -> str:
    """The n-th G-code line a client sends: a small Z move, unique by its value."""
    return f"G0 Z0.{n:03d}"


@dataclass(frozen=True, slots=True)
class Context:
    """What a client line is admitted in: it must be written in the same one."""

    holds_ended: int  # holds the host ended (or saw end) so far
    in_hold: bool  # the host last read HOLD from the board
    operations: int  # operations started so far
    lockouts: int  # lockouts the host has read so far


@dataclass
class Observer:
    machine: Machine
    window: int
    violations: dict[str, list[str]] = field(default_factory=lambda: defaultdict(list))
    step: int = 0  # the step of the state machine that runs now (0: setting up)
    tx: list[str] = field(default_factory=list)  # everything written, in order
    settings_rows: set[int] = field(default_factory=set)
    # The host's view, updated event by event.
    _locked: bool = False
    _lockouts: int = 0
    _in_hold: bool = False
    _stat: int | None = None  # the last `stat` read
    _hold: int = 0  # the last `hold` read (g2core's hold state; 0: none)
    _holds_ended: int = 0
    _operations: int = 0
    _op_job: int | None = None  # the job row of the operation that runs now
    _jobs: dict[int, dict[str, Any]] = field(default_factory=dict)  # last published, by id
    _written: dict[int, int] = field(default_factory=dict)  # job file -> last line written
    _ended_files: set[int] = field(default_factory=set)
    _admitted: dict[str, Context] = field(default_factory=dict)  # client line -> context
    _data_out: int = 0  # data lines written since the count was last known to be exact
    _answers: int = 0  # answers read since then

    def fail(self, rule: str, text: str) -> None:
        self.violations[rule].append(f"[step {self.step}] {text}")

    def context(self) -> Context:
        return Context(self._holds_ended, self._in_hold, self._operations, self._lockouts)

    def admit(self, line: str) -> None:
        """A client asks for `line` now (called in the step the engine admits it)."""
        self._admitted[line] = self.context()

    def job_state(self, job_id: int) -> str | None:
        job = self._jobs.get(job_id)
        return None if job is None else str(job["state"])

    @property
    def operation_job(self) -> int | None:
        return self._op_job

    # -- events ------------------------------------------------------------

    def __call__(self, event: Event) -> None:
        supervisor = self.machine.supervisor.state.value
        if isinstance(event, Console):
            if event.direction == "tx":
                self._written_line(event.text, supervisor)
            elif event.text.startswith('{"r":') and "SYSTEM READY" not in event.text:
                self._answers += 1
        elif isinstance(event, StatusChanged):
            self._status(event.report)
        elif isinstance(event, LinkChanged):
            if not event.up:
                # The link is gone: what the host read of the board no longer holds. Not
                # when it comes up: the handshake's reports come before that event, and
                # they are what the host knows of the board in the new connection (a
                # hold at rest, `hold` 10, read there, lets in-hold lines go).
                self._locked = False
                self._stat, self._hold = None, 0
                self._end_hold()
            self._data_out = self._answers = 0  # the handshake's answers are none of a line's
        elif isinstance(event, SupervisorChanged):
            self._supervisor(event)
        elif isinstance(event, JobChanged):
            self._job(event.job, supervisor)
        elif isinstance(event, FaultChanged):
            fault = event.fault
            if fault["id"] == "internal" and fault["active"]:
                self.fail("daemon", f"internal fault: {fault['message']}")

    def _status(self, report: dict[str, Any]) -> None:
        # Reports carry only what changed: `stat` and `hold` are each kept from the last
        # report that had it. A `!` at rest on 101.05+ leaves `stat` as it was and shows
        # the hold in `hold` alone; the host takes that for a hold too (gc2 lines go).
        stat, hold = report.get("stat"), report.get("hold")
        if isinstance(hold, int):
            self._hold = hold
        if isinstance(stat, int):
            self._stat = stat
            locked = stat in LOCKOUT
            if locked and not self._locked:
                self._lockouts += 1
            self._locked = locked
        elif not isinstance(hold, int):
            return
        if self._stat == MachineState.HOLD or (self._hold and not self._locked):
            self._in_hold = True
        else:
            self._end_hold()

    def _end_hold(self) -> None:
        if self._in_hold:
            self._holds_ended += 1
        self._in_hold = False

    def _supervisor(self, event: SupervisorChanged) -> None:
        if event.event == "start-operation":
            self._operations += 1
            self._op_job = None
        elif event.event == "operation-stopped" and self._op_job is not None:
            state = self.job_state(self._op_job)
            if state not in FINAL:
                self.fail(
                    "supervisor",
                    f"the operation stopped while its job {self._op_job} is still {state}",
                )
        if event.target not in ("operation", "paused"):
            self._op_job = None

    # -- what the engine wrote --------------------------------------------

    def _written_line(self, text: str, supervisor: str) -> None:
        self.tx.append(text)
        if text in REALTIME:
            if text in HOLD_ENDS:
                self._holds_ended += 1
            if text in FORGETS:
                self._data_out = self._answers = 0
            return
        job = _JOB_LINE.fullmatch(text)
        if job is not None:
            self._job_line(int(job.group(1)), int(job.group(2)), supervisor)
        else:
            self._client_line(text, supervisor)
        if not text.startswith("{"):
            self._data_out += 1

    def _job_line(self, file: int, line: int, supervisor: str) -> None:
        where = f"line {line} of {job_file(file)}"
        last = self._written.get(file, 0)
        self._written[file] = max(last, line)
        if line != last + 1:
            self.fail("stream", f"{where} written after line {last}: twice, skipped or reordered")
        if file in self._ended_files:
            self.fail("stream", f"{where} written after its job ended")
        if supervisor == "paused":
            self.fail("paused", f"{where} written while the job is paused")
        elif supervisor != "operation":
            self.fail("stream", f"{where} written while the supervisor is {supervisor}")
        if self._locked:
            self.fail("lockout", f"{where} written after the host read a lockout")
        unanswered = self._data_out - self._answers  # a lower bound: answers may be a query's
        if unanswered >= self.window:
            self.fail("window", f"{where} written with {unanswered} lines unanswered")

    def _client_line(self, text: str, supervisor: str) -> None:
        in_hold = False
        if text.startswith('{"gc2":'):
            text = str(json.loads(text)["gc2"])
            in_hold = True
        if not _CLIENT_LINE.fullmatch(text):
            return
        admitted = self._admitted.get(text)
        if admitted is None:
            self.fail("client", f"{text!r} written, but no client asked for it")
            return
        now = self.context()
        what = f"client line {text!r}" + (" (in-hold)" if in_hold else "")
        if self._locked or now.lockouts != admitted.lockouts:
            self.fail("client", f"{what} written after a lockout began")
        if in_hold:
            if now.holds_ended != admitted.holds_ended:
                self.fail("in-hold", f"{what} written after the hold it was admitted in ended")
            elif not now.in_hold:
                self.fail("in-hold", f"{what} written before the host read HOLD from the board")
        elif supervisor in ("operation", "paused") or now.operations != admitted.operations:
            self.fail("client", f"{what} written inside an operation (supervisor {supervisor})")

    # -- what clients were told of jobs -----------------------------------

    def _job(self, job: dict[str, Any], supervisor: str) -> None:
        job_id = int(job["id"])
        state = job["state"]
        name = f"job {job_id} ({job['kind']})"
        before = self._jobs.get(job_id)
        if before is not None and before["state"] in FINAL:
            kept = ("state", "ended_at", "lines_acked", "lines_sent")
            if any(job[k] != before[k] for k in kept):
                changed = {k: (before[k], job[k]) for k in kept if job[k] != before[k]}
                self.fail("final", f"{name} changed after it ended {before['state']}: {changed}")
        if (job["ended_at"] is not None) != (state in FINAL):
            self.fail("final", f"{name} is {state} with ended_at {job['ended_at']}")
        acked, total = job["lines_acked"], job["lines_total"]
        if before is not None and acked < before["lines_acked"]:
            self.fail("acked", f"{name}: lines_acked went from {before['lines_acked']} to {acked}")
        if state == "completed" and acked != total:
            self.fail("completed", f"{name} completed with {acked} of {total} lines answered")
        if state in ("running", "paused") and supervisor not in LIVE:
            self.fail("supervisor", f"{name} published {state}; the supervisor is {supervisor}")
        if job["kind"] == "settings":
            self.settings_rows.add(job_id)
        if self._op_job is None and before is None and supervisor in ("operation", "paused"):
            self._op_job = job_id  # the first row published after start-operation
        if state in FINAL and job["file"] is not None:
            self._ended_files.add(int(job["file"].removeprefix("job").removesuffix(".gcode")))
        self._jobs[job_id] = dict(job)
