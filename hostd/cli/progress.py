"""Following a running job: the live progress display and the Ctrl-C questions.

`follow_job` reads the `job`, `status` and `exception` notifications of the
job's machine (the caller subscribed before starting the job, so none are
missed) until the job reaches an end state, and returns the final job row.
If the notifications go quiet it asks `job.get` itself, so a lost or late
event can delay the display but never hang the client.

On a terminal the display is a rich progress bar (lines answered of the
total, percentage, rate, ETA, machine state and the line the board says it
runs, `line_executed`); once every line is answered
and the job still runs, the ETA says "finishing" (the board's planner still
holds moves; `RemainingColumn`), as the dashboard does. Elsewhere it is a plain line
on every job state change and every tenth of the way: logs and pipes get
a readable history instead of a redrawn bar.

Ctrl-C while following asks "pause, cancel or continue?". After a pause the
question becomes "resume, cancel or stay paused?".

A job that holds at a tool change (the machine's `tool_change` policy,
docs/operations.md) shows "Change to tool 2 (line 57), then press Enter";
Enter answers it with `job.tool_change_done`. Without input to read (stdin
at its end: a script, a service) the prompt says how to answer from
elsewhere (`hostd tool-change-done MACHINE`) and the client goes on
following: the job continues once someone answers. A second Ctrl-C at a
question, or the end of stdin, stops following (the job goes on; the
client says so and how to stop it): only an explicit answer touches the job.
"""

from __future__ import annotations

import time
from typing import Any, Final

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    ProgressColumn,
    Task,
    TaskID,
    TaskProgressColumn,
    TextColumn,
    TimeRemainingColumn,
)
from rich.text import Text

from hostd.cli import render
from hostd.cli.client import Client, Notification, RpcError
from hostd.cli.interactive import CtrlC, Interrupted, StdinLines, unless_interrupted

ENDED: Final = frozenset({"completed", "failed", "cancelled", "interrupted"})
# Quiet time after which the job row is asked for instead of waited for.
POLL_AFTER: Final = 1.0


class Detached(Exception):
    """The operator stopped following without touching the job (second Ctrl-C, or EOF)."""


class RateColumn(ProgressColumn):
    """Lines answered per second, as rich estimates it over its recent samples."""

    def render(self, task: Task) -> Text:
        speed = task.speed
        return Text("   - lines/s" if speed is None else f"{speed:5.0f} lines/s")


class RemainingColumn(TimeRemainingColumn):
    """The time left at the current rate, until every line is answered: then the job is
    "finishing" while it runs (the board works through what its planner holds; a job
    completes only when the board rests), where a countdown would say 0:00:00."""

    def render(self, task: Task) -> Text:
        if task.total is not None and task.completed >= task.total and task.fields.get("running"):
            return Text("finishing", style="progress.remaining")
        return super().render(task)


class JobDisplay:
    """The job's progress where the user can see it: a live bar, or plain lines."""

    def __init__(self, console: Console, job: dict[str, Any]) -> None:
        self.console = console
        self._acked = 0
        self._state = str(job.get("state"))
        self._machine_state = "?"
        self._tenth = -1
        self._progress: Progress | None = None
        self._task_id = TaskID(0)
        if console.is_terminal:
            self._progress = Progress(
                TextColumn("[bold]{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TaskProgressColumn(),
                RateColumn(),
                RemainingColumn(),
                TextColumn("{task.fields[where]}"),
                console=console,
                transient=False,
            )
            name = f"#{job.get('id')} {job.get('file') or ''}".strip()
            self._task_id = self._progress.add_task(
                name, total=job.get("lines_total"), where="", running=self._state == "running"
            )

    def __enter__(self) -> JobDisplay:
        if self._progress is not None:
            self._progress.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._progress is not None:
            self._progress.stop()

    def hide(self) -> None:
        """Stop redrawing while the user answers a question."""
        if self._progress is not None:
            self._progress.stop()

    def show(self) -> None:
        if self._progress is not None:
            self._progress.start()

    def update(self, job: dict[str, Any], machine_state: str | None = None) -> None:
        # lines_acked never goes backwards (api.md); a late poll must not make the bar do so.
        self._acked = max(self._acked, int(job.get("lines_acked") or 0))
        if machine_state is not None:
            self._machine_state = machine_state
        state = str(job.get("state"))
        total = job.get("lines_total")
        if self._progress is not None:
            where = (
                self._machine_state if state == "running" else f"{state} · {self._machine_state}"
            )
            at = job.get("line_executed")
            if isinstance(at, int) and state in ("running", "paused"):
                where += f" · line {at}"  # the board's place: answered lines are only planned
            self._progress.update(
                self._task_id,
                completed=self._acked,
                total=total,
                where=where,
                running=state == "running",
            )
            return
        if state != self._state:
            self._state = state
            self.note(f"job #{job.get('id')} {state}: {render.lines(job)}")
        elif isinstance(total, int) and total > 0:
            tenth = min(10, self._acked * 10 // total)
            if tenth > self._tenth:
                self._tenth = tenth
                if 0 < tenth < 10:
                    self.note(f"job #{job.get('id')} {state}: {render.lines(job)}")

    def note(self, text: str) -> None:
        """A line above the bar (or just a line): exceptions, state changes."""
        self.console.print(text, markup=False, highlight=False, soft_wrap=True)


class JobFollower:
    """Reads one job's notifications to its end, answering Ctrl-C with a question."""

    def __init__(
        self,
        client: Client,
        machine: str,
        job_id: int,
        *,
        console: Console,
        ctrl_c: CtrlC,
        answers: StdinLines,
    ) -> None:
        self.client = client
        self.machine = machine
        self.job_id = job_id
        self.console = console
        self.ctrl_c = ctrl_c
        self.answers = answers
        self._notes = client.notifications()
        self._asked_at: int | None = None  # the M6 line last prompted for
        self._no_input = False  # stdin ended: tool changes are answered elsewhere

    async def follow(self) -> dict[str, Any]:
        """The job's final row, once it has ended."""
        job: dict[str, Any] = await self.client.call("job.get", job=self.job_id)
        with JobDisplay(self.console, job) as display:
            display.update(job)
            news_at = time.monotonic()
            while job.get("state") not in ENDED:
                wait = max(0.0, news_at + POLL_AFTER - time.monotonic())
                try:
                    note = await unless_interrupted(self._notes.__anext__(), self.ctrl_c, wait)
                except Interrupted:
                    self.ctrl_c.clear()
                    job = await self._ask(display, job)
                    continue
                except TimeoutError:
                    note = None
                if note is None:  # quiet for POLL_AFTER: ask rather than wait
                    job = await self.client.call("job.get", job=self.job_id)
                    news_at = time.monotonic()
                elif (row := self._apply(display, note, job)) is not None:
                    job = row
                    news_at = time.monotonic()
                display.update(job)
                if job.get("state") == "paused":
                    job = await self._tool_change(display, job)
                else:
                    self._asked_at = None
        return job

    async def _tool_change(self, display: JobDisplay, job: dict[str, Any]) -> dict[str, Any]:
        """A paused job that waits at a tool change: prompt, and answer on Enter."""
        snapshot = await self.client.call("machine.status", machine=self.machine)
        change = snapshot.get("tool_change") if isinstance(snapshot, dict) else None
        if not isinstance(change, dict) or change.get("line") == self._asked_at:
            return job
        self._asked_at = change.get("line")
        tool = change.get("tool")
        what = f"Change to tool {tool}" if tool is not None else "Change the tool"
        display.hide()
        try:
            if self._no_input:
                self._hint(what, change)
                return job
            self.console.print(
                f"{what} (line {change.get('line')}), then press Enter",
                markup=False,
                highlight=False,
            )
            while True:
                try:
                    line = await unless_interrupted(self.answers.readline(), self.ctrl_c)
                except Interrupted:
                    self.ctrl_c.clear()
                    return await self._ask(display, job)
                if line is None:
                    self._no_input = True
                    self._hint(what, change)
                    return job
                try:
                    row: dict[str, Any] = await self.client.call(
                        "job.tool_change_done", machine=self.machine
                    )
                except RpcError as exc:
                    self.console.print(
                        f"job.tool_change_done: {exc.message} ({exc.code}); press Enter to retry",
                        markup=False,
                    )
                    continue
                return row if row.get("id") == self.job_id else job
        finally:
            display.show()

    def _hint(self, what: str, change: dict[str, Any]) -> None:
        self.console.print(
            f"{what} (line {change.get('line')}), then answer with "
            f"`hostd tool-change-done {self.machine}`",
            markup=False,
            highlight=False,
        )

    def _apply(
        self, display: JobDisplay, note: Notification, job: dict[str, Any]
    ) -> dict[str, Any] | None:
        """Take in one notification; the new job row when it was news of our job."""
        params = note.params
        if note.method == "job":
            row = params.get("job")
            if isinstance(row, dict) and row.get("id") == self.job_id:
                return row
        elif note.method == "status":
            snapshot = params.get("snapshot")
            if isinstance(snapshot, dict):
                display.update(job, render.state_name(snapshot))
        elif note.method == "exception":
            report = render.json_line(params.get("report"))
            display.note(f"{self.machine}: controller exception {report}")
        return None

    async def _ask(self, display: JobDisplay, job: dict[str, Any]) -> dict[str, Any]:
        """Ctrl-C: ask what to do with the job; returns the job row after the answer."""
        display.hide()
        try:
            while job.get("state") not in ENDED:
                paused = job.get("state") == "paused"
                if paused:
                    question = (
                        f"job #{self.job_id} paused: resume, cancel or stay paused? [r/c/Enter]"
                    )
                else:
                    question = f"job #{self.job_id}: pause, cancel or continue? [p/c/Enter]"
                answer = await self._answer(question)
                if answer == "":
                    return job
                if answer in ("c", "cancel"):
                    return await self._act("job.cancel", job)
                if answer in ("p", "pause") and not paused:
                    job = await self._act("job.pause", job)
                    continue  # offer resume straight away
                if answer in ("r", "resume") and paused:
                    return await self._act("job.resume", job)
                self.console.print(f"answer with {'r' if paused else 'p'}, c or Enter")
            return job
        finally:
            display.show()

    async def _answer(self, question: str) -> str:
        self.console.print(question, markup=False, highlight=False)
        try:
            line = await unless_interrupted(self.answers.readline(), self.ctrl_c)
        except Interrupted:
            self.ctrl_c.clear()
            line = None
        if line is None:
            raise Detached
        return line.strip().lower()

    async def _act(self, method: str, job: dict[str, Any]) -> dict[str, Any]:
        """Pause, resume or cancel; a refusal (the job ended meanwhile) is shown, not fatal."""
        try:
            row: dict[str, Any] = await self.client.call(method, machine=self.machine)
        except RpcError as exc:
            self.console.print(f"{method}: {exc.message} ({exc.code})", markup=False)
            row = await self.client.call("job.get", job=self.job_id)  # where it stands now
        return row if row.get("id") == self.job_id else job
