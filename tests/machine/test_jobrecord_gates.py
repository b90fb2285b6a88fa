"""What a job's row on disk says at the moments that matter: a pause, a burst of answers,
the job's end, a stop of the daemon, a crash, a disk that refuses a write.

The job runner (jobrunner.py) is driven here with a real SQLite file and an engine that
sends nothing: the test plays the board, setting the stream's counts as a board's
answers would and ending it as the session would. The runner's clock-driven writes are
switched off (`PERSIST_EVERY` and `PUBLISH_EVERY` an hour), so a row that changes on
disk changed for the cause the test gave it, and a test waits for that write, never for
time to pass.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import sqlite3
import subprocess
import sys
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import pytest

from hostd.machine import jobrunner
from hostd.machine.engine import Engine
from hostd.machine.events import Event, Hub, JobChanged
from hostd.machine.jobrunner import JobRunner
from hostd.machine.jobstore import Job, JobStore, ToolChange
from hostd.machine.stream import JobStream
from hostd.protocol.errors import MachineError, NotConnected
from hostd.protocol.vocabulary import StreamEnd, StreamResult

pytestmark = pytest.mark.asyncio

ENDED = ("completed", "failed", "cancelled", "interrupted")


class QuietEngine:
    """An engine that takes a job's stream and sends nothing (or refuses it, as a board
    that cannot take a job would): the test plays the board."""

    def __init__(self, refuse: MachineError | None = None) -> None:
        self.refuse = refuse
        self.streams: list[JobStream] = []

    def start_stream(self, stream: JobStream) -> None:
        if self.refuse is not None:
            raise self.refuse
        self.streams.append(stream)


class WatchedStore(JobStore):
    """The job store, saying when it wrote; a disk that refuses, when told to."""

    def __init__(self, path: Path) -> None:
        super().__init__(path)
        self.wrote = asyncio.Event()
        self.refuse_create = False
        self.refuse_write = False

    async def create(self, *args: Any, **kwargs: Any) -> Job:
        if self.refuse_create:
            raise sqlite3.OperationalError("disk I/O error")
        return await super().create(*args, **kwargs)

    async def write(self, job_id: int, **fields: Any) -> None:
        try:
            if self.refuse_write:
                raise sqlite3.OperationalError("database or disk is full")
            await super().write(job_id, **fields)
        finally:
            self.wrote.set()

    async def until(self, job_id: int, predicate: Callable[[Job], bool]) -> Job:
        """The row once a write made `predicate` true (5 s bounds a hang, no timing)."""
        async with asyncio.timeout(5):
            while True:
                self.wrote.clear()
                row = await self.get(job_id)
                if row is not None and predicate(row):
                    return row
                await self.wrote.wait()


def on_disk(path: Path, job_id: int) -> dict[str, Any]:
    """The row as another process would read it now, from the file, at once (no await)."""
    with contextlib.closing(sqlite3.connect(path)) as db:
        db.row_factory = sqlite3.Row
        row = db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
    return dict(row) if row is not None else {}


@dataclass
class Desk:
    """One machine's job runner, serving in a task group of its own (a Machine's)."""

    runner: JobRunner
    store: WatchedStore
    engine: QuietEngine
    path: Path
    task: asyncio.Task[None] | None = None
    busy: bool = False
    freed: asyncio.Event = field(default_factory=asyncio.Event)
    # What happened, in order: ("told", state, the row's state on disk then), ("freed", ...).
    seen: list[tuple[str, str, str | None]] = field(default_factory=list)
    told: list[dict[str, Any]] = field(default_factory=list)  # every job event's job

    async def start(self) -> tuple[Job, JobStream]:
        job = await self.runner.start("make", "part.nc", 500, iter(()), None)
        return job, self.engine.streams[-1]

    async def stop(self) -> None:
        """The machine stops (the daemon's SIGTERM): its task group is cancelled."""
        assert self.task is not None
        self.task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self.task


@pytest.fixture(autouse=True)
def no_clock(monkeypatch: pytest.MonkeyPatch) -> None:
    """No write or tell for time alone: what a test finds written, its own step caused."""
    monkeypatch.setattr(jobrunner, "PERSIST_EVERY", 3600.0)
    monkeypatch.setattr(jobrunner, "PUBLISH_EVERY", 3600.0)


@contextlib.asynccontextmanager
async def desk_for(tmp_path: Path, engine: QuietEngine | None = None) -> AsyncIterator[Desk]:
    path = tmp_path / "jobs.db"
    store = WatchedStore(path)
    hub = Hub()
    quiet = engine or QuietEngine()

    def begin() -> None:
        desk.busy = True
        desk.freed.clear()

    def end() -> None:
        desk.busy = False
        job = desk.runner.job
        state = None if job is None else on_disk(path, job.id).get("state")
        desk.seen.append(("freed", "", state))
        desk.freed.set()

    def told(event: Event) -> None:
        if not isinstance(event, JobChanged):
            return
        desk.told.append(event.job)
        if event.job["state"] in ENDED:
            state = on_disk(path, event.job["id"]).get("state")
            desk.seen.append(("told", event.job["state"], state))

    hub.subscribe(told)
    runner = JobRunner(
        "m1", cast(Engine, quiet), store, hub, begin_operation=begin, end_operation=end
    )
    desk = Desk(runner, store, quiet, path)
    serving = asyncio.Event()

    async def serve() -> None:
        async with asyncio.TaskGroup() as group:
            with runner.serving(group):
                serving.set()
                await asyncio.Event().wait()

    desk.task = asyncio.create_task(serve())
    try:
        await serving.wait()
        yield desk
    finally:
        await desk.stop()
        store.close()


async def settled(stream: JobStream) -> None:
    """Until the job's follower has set its line mark (its write gap over) and sleeps:
    from now on only an answer that crosses the mark, or a change, wakes it."""
    async with asyncio.timeout(5):
        while stream.wake_at is None:  # noqa: ASYNC110 (the follower sets it, no event)
            await asyncio.sleep(0.005)


def answered(stream: JobStream, sent: int, acked: int, executing: int | None) -> None:
    """The board took `sent` lines, answered `acked`, said it runs file line `executing`."""
    position = stream.position
    position.sent, position.acked, position.line_executed = sent, acked, executing
    position.last_acked_line = acked
    stream.stepped()


def ends(stream: JobStream, result: StreamResult) -> None:
    stream.position.done = True
    stream.ended(result)


async def test_a_pause_and_a_tool_change_reach_the_row_at_once_while_no_line_moves(
    tmp_path: Path,
) -> None:
    """A paused job (no line answered for minutes) says `paused` on disk, and a tool change
    the operator made is on disk as soon as the job goes on: not at the next progress."""
    async with desk_for(tmp_path) as desk:
        job, stream = await desk.start()
        await settled(stream)
        answered(stream, sent=9, acked=4, executing=3)  # under the mark: nothing written
        paused = desk.runner.change(state="paused")
        assert (paused.state, paused.lines_acked, paused.line_executed) == ("paused", 4, 3)
        assert (await desk.store.until(job.id, lambda r: r.state == "paused")).lines_acked == 4
        change = ToolChange(tool=2, line=40, at="2026-11-29T05:00:00.000Z")
        desk.runner.change(state="running", tool_changes=[change])
        row = await desk.store.until(
            job.id, lambda r: r.state == "running" and bool(r.tool_changes)
        )
        assert row.tool_changes == [change]


async def test_a_job_is_told_running_as_soon_as_its_row_is_written(tmp_path: Path) -> None:
    """A subscriber hears of a new job at once, not at its first answered line (a board
    that takes its time, a long first move)."""
    async with desk_for(tmp_path) as desk:
        job, _ = await desk.start()
        assert [(told["id"], told["state"]) for told in desk.told] == [(job.id, "running")]
        assert on_disk(desk.path, job.id)["state"] == "running"


async def test_a_burst_of_answered_lines_is_written_at_once_not_at_the_next_second(
    tmp_path: Path,
) -> None:
    """A laser raster answers a thousand lines a second: a crash must not lose more than
    100 of them (`PERSIST_LINES`). The row keeps what was sent, answered and executing
    apart."""
    async with desk_for(tmp_path) as desk:
        job, stream = await desk.start()
        await settled(stream)
        answered(stream, sent=160, acked=150, executing=140)
        row = await desk.store.until(job.id, lambda r: r.lines_acked > 0)
        assert (row.state, row.lines_sent, row.lines_acked, row.line_executed) == (
            "running",
            160,
            150,
            140,
        )


async def test_a_stopped_daemon_ends_the_job_interrupted_with_the_counts_it_last_had(
    tmp_path: Path,
) -> None:
    """The daemon stops mid-job: the row says `interrupted` (1002) with the lines answered
    and the line executing at that moment, not those of the last progress write. A resume
    starts at that line, so an old one would run lines again."""
    async with desk_for(tmp_path) as desk:
        job, stream = await desk.start()
        await settled(stream)
        answered(stream, sent=12, acked=7, executing=5)  # under the mark: nothing written
        await desk.stop()
        row = on_disk(desk.path, job.id)
        assert (row["state"], row["lines_sent"], row["lines_acked"], row["line_executed"]) == (
            "interrupted",
            12,
            7,
            5,
        )
        assert (row["error_code"], row["error_message"]) == (
            1002,
            "the daemon stopped during the job",
        )
        assert row["ended_at"] is not None and not desk.busy


async def test_a_job_is_told_ended_only_once_its_end_is_on_disk_then_the_machine_is_free(
    tmp_path: Path,
) -> None:
    """No client hears `completed` of a job a crash would then show `interrupted`, and a
    client that finds the machine free finds the job's end on disk. A completed job ran
    every line the board answered: that is its `line_executed`."""
    async with desk_for(tmp_path) as desk:
        job, stream = await desk.start()
        answered(stream, sent=3, acked=3, executing=2)
        ends(stream, StreamResult(StreamEnd.COMPLETED))
        async with asyncio.timeout(5):
            await desk.freed.wait()
        assert desk.seen == [("told", "completed", "completed"), ("freed", "", "completed")]
        row = on_disk(desk.path, job.id)
        assert (row["lines_acked"], row["line_executed"], row["error_code"]) == (3, 3, None)


async def test_a_job_cancelled_just_after_its_pause_ends_cancelled_not_paused(
    tmp_path: Path,
) -> None:
    """The pause is not yet on disk when the job ends (its follower not woken yet): the
    end, not the pause, is the row's last word."""
    async with desk_for(tmp_path) as desk:
        job, stream = await desk.start()
        desk.runner.change(state="paused")
        ends(stream, StreamResult(StreamEnd.CANCELLED))
        async with asyncio.timeout(5):
            await desk.freed.wait()
        assert on_disk(desk.path, job.id)["state"] == "cancelled"
        assert desk.runner.job is not None and desk.runner.job.state == "cancelled"


async def test_a_settings_batch_is_told_and_written_line_by_line(tmp_path: Path) -> None:
    """An operation that waits for each line (settings) has each answer on disk and told
    before the next line goes: a crash mid-batch shows how far it got."""
    async with desk_for(tmp_path) as desk:
        job = await desk.runner.begin("settings", None, 3)
        await desk.runner.save(lines_sent=1, lines_acked=1)
        assert (on_disk(desk.path, job.id)["lines_acked"], desk.told[-1]["lines_acked"]) == (1, 1)
        await desk.runner.end(StreamResult(StreamEnd.COMPLETED))


async def test_the_job_file_is_closed_when_the_job_ends(tmp_path: Path) -> None:
    """A daemon that runs jobs for weeks keeps no file of a finished job open."""
    (tmp_path / "part.nc").write_text("G0 X1\n")
    async with desk_for(tmp_path) as desk:
        handle = (tmp_path / "part.nc").open()
        await desk.runner.start("make", "part.nc", 1, iter(()), handle)
        ends(desk.engine.streams[-1], StreamResult(StreamEnd.COMPLETED))
        async with asyncio.timeout(5):
            await desk.freed.wait()
        assert handle.closed


async def test_a_job_whose_stream_ended_is_no_longer_live_before_its_end_is_written(
    tmp_path: Path,
) -> None:
    """A pause that arrives between the board's end of the job and the row's end finds no
    live job (1003), rather than a `paused` the row's end would then overwrite."""
    async with desk_for(tmp_path) as desk:
        _, stream = await desk.start()
        assert desk.runner.live() is stream
        ends(stream, StreamResult(StreamEnd.COMPLETED))
        assert desk.runner.live() is None


async def test_the_end_of_a_cancelled_job_is_on_disk_once_its_followers_are_done(
    tmp_path: Path,
) -> None:
    """job.cancel answers once `followed` returns: by then the row says `cancelled`."""
    async with desk_for(tmp_path) as desk:
        job, stream = await desk.start()
        ends(stream, StreamResult(StreamEnd.CANCELLED))
        await desk.runner.followed(timeout=5)
        assert on_disk(desk.path, job.id)["state"] == "cancelled"


async def test_a_job_the_board_refuses_to_start_is_recorded_failed_and_frees_the_machine(
    tmp_path: Path,
) -> None:
    refusal = MachineError("the board cannot take a job now")
    async with desk_for(tmp_path, QuietEngine(refuse=refusal)) as desk:
        with pytest.raises(MachineError):
            await desk.start()
        (row,) = await desk.store.list_jobs()
        assert row.state == "failed" and row.ended_at is not None
        assert row.error is not None and row.error.code == refusal.code
        assert not desk.busy


async def test_a_row_that_cannot_be_created_leaves_the_machine_free(tmp_path: Path) -> None:
    """A disk that refuses the new row refuses the job, not every job after it."""
    async with desk_for(tmp_path) as desk:
        desk.store.refuse_create = True
        with pytest.raises(sqlite3.OperationalError):
            await desk.start()
        assert not desk.busy


async def test_a_row_that_cannot_be_written_still_ends_the_job_and_frees_the_machine(
    tmp_path: Path,
) -> None:
    """A full disk loses the row's end, not the machine: it is told ended, and free."""
    async with desk_for(tmp_path) as desk:
        _, stream = await desk.start()
        desk.store.refuse_write = True
        ends(stream, StreamResult(StreamEnd.COMPLETED))
        async with asyncio.timeout(5):
            await desk.freed.wait()
        assert desk.runner.job is not None and desk.runner.job.state == "completed"
        assert [told for told in desk.seen if told[0] == "told"] == [
            ("told", "completed", "running")
        ]


async def test_no_job_starts_and_no_row_is_written_once_the_machine_has_stopped(
    tmp_path: Path,
) -> None:
    async with desk_for(tmp_path) as desk:
        await desk.stop()
        with pytest.raises(NotConnected):
            await desk.start()
        assert await desk.store.list_jobs() == [] and not desk.busy


async def test_the_next_start_finds_a_lost_job_interrupted_with_why(tmp_path: Path) -> None:
    """What a restart tells of a job the dead daemon was running: `interrupted`, 1002."""
    path = tmp_path / "jobs.db"
    store = JobStore(path)
    job = await store.create("m1", "make", "part.nc", 500)
    await store.write(job.id, lines_sent=60, lines_acked=50, line_executed=48)
    store.close()
    store = JobStore(path)
    try:
        (lost,) = await store.recover()
        row = await store.get(job.id)
    finally:
        store.close()
    assert lost == row  # told as it is on disk: its end time and its error too
    assert row is not None and row.state == "interrupted" and row.ended_at is not None
    assert row.error is not None
    assert (row.error.code, row.error.message) == (1002, "the daemon stopped during the job")
    assert (row.lines_sent, row.lines_acked, row.line_executed) == (60, 50, 48)


_CRASH = """
import asyncio, os, sys
from hostd.machine.jobstore import JobStore

async def main():
    store = JobStore(sys.argv[1])
    job = await store.create("m1", "make", "part.nc", 500)
    await store.write(job.id, lines_sent=60, lines_acked=50, line_executed=48)
    os._exit(0)  # killed: no close, no clean exit

asyncio.run(main())
"""


async def test_a_row_written_before_a_crash_is_found_by_the_next_start(tmp_path: Path) -> None:
    """The daemon's process dies just after a progress write: the next start finds the job
    with that progress (a committed write, not one held back until a clean close)."""
    path = tmp_path / "jobs.db"
    done = await asyncio.to_thread(
        subprocess.run, [sys.executable, "-c", _CRASH, str(path)], timeout=60, check=False
    )
    assert done.returncode == 0
    store = JobStore(path)
    try:
        (lost,) = await store.recover()
    finally:
        store.close()
    assert (lost.state, lost.lines_sent, lost.lines_acked, lost.line_executed) == (
        "interrupted",
        60,
        50,
        48,
    )


async def test_the_job_file_keeps_a_write_ahead_log_synced_at_least_normally(
    tmp_path: Path,
) -> None:
    """WAL with synchronous NORMAL (or FULL): a committed row survives a killed daemon,
    and only a power cut may lose the last commits (OFF would lose them to an OS crash)."""
    store = JobStore(tmp_path / "jobs.db")
    try:
        synchronous = store._db.execute("PRAGMA synchronous").fetchone()[0]
    finally:
        store.close()
    with contextlib.closing(sqlite3.connect(tmp_path / "jobs.db")) as db:
        assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert synchronous >= 1  # 0 OFF, 1 NORMAL, 2 FULL, 3 EXTRA


async def test_one_machines_progress_leaves_the_other_machines_row_as_it_was(
    tmp_path: Path,
) -> None:
    """Two machines share the daemon's one job file: each job's writes touch its row only."""
    store = JobStore(tmp_path / "jobs.db")
    try:
        first = await store.create("laser1", "make", "a.nc", 500)
        second = await store.create("mill1", "make", "b.nc", 800)
        await store.write(second.id, lines_sent=30, lines_acked=20, line_executed=18)
        await store.write(first.id, lines_sent=400, lines_acked=390, state="paused")
        other = await store.get(second.id)
    finally:
        store.close()
    assert other is not None
    assert (other.state, other.lines_sent, other.lines_acked, other.line_executed) == (
        "running",
        30,
        20,
        18,
    )


async def test_a_jobs_times_are_utc_to_the_millisecond(tmp_path: Path) -> None:
    """A jog lasts less than a second: its times keep the milliseconds that tell its start
    from its end, in UTC (`Z`)."""
    store = JobStore(tmp_path / "jobs.db")
    try:
        job = await store.create("m1", "jog", None, 2)
    finally:
        store.close()
    assert job.started_at is not None
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z", job.started_at)


async def test_a_failing_follower_of_a_job_does_not_stop_the_machine(tmp_path: Path) -> None:
    """A bug in a job's other follower (its tool changes) is logged: the machine goes on
    serving, and its next job starts and is recorded."""

    async def broken() -> None:
        raise RuntimeError("a tool-change follower's own failure")

    async with desk_for(tmp_path) as desk:
        desk.runner.follow_also(broken(), "m1-tools")
        await desk.runner.followed(timeout=5)
        job, stream = await desk.start()
        ends(stream, StreamResult(StreamEnd.COMPLETED))
        await desk.runner.followed(timeout=5)
        assert on_disk(desk.path, job.id)["state"] == "completed"
        await desk.stop()  # the machine's group ends cancelled, not with the failure
