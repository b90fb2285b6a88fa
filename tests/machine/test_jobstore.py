"""The job store on a real SQLite file."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from hostd.machine.jobstore import JobError, JobStore, ToolChange

pytestmark = pytest.mark.asyncio


async def test_a_job_row_round_trips(tmp_path: Path) -> None:
    store = JobStore(tmp_path / "jobs.db")
    job = await store.create("laser1", "make", "part.gcode", 120)
    assert (job.state, job.lines_total, job.lines_acked) == ("running", 120, 0)
    assert job.started_at is not None and job.started_at.endswith("Z")
    job = await store.update(job.id, lines_sent=10, lines_acked=8)
    job = await store.update(
        job.id,
        state="failed",
        ended_at="2026-11-22T00:00:00.000Z",
        error=JobError(code=204, message="alarm"),
    )
    again = await store.get(job.id)
    assert again == job
    assert again is not None and again.error == JobError(code=204, message="alarm")
    assert again.model_dump()["error"] == {"code": 204, "message": "alarm"}
    store.close()


async def test_list_is_newest_first_and_filters_by_machine(tmp_path: Path) -> None:
    store = JobStore(tmp_path / "jobs.db")
    ids = [(await store.create(m, "jog", None, None)).id for m in ("a", "b", "a")]
    assert [j.id for j in await store.list_jobs()] == ids[::-1]
    assert [j.id for j in await store.list_jobs("a")] == [ids[2], ids[0]]
    assert [j.id for j in await store.list_jobs(limit=1)] == [ids[2]]
    store.close()


async def test_rows_left_running_become_interrupted_on_the_next_start(tmp_path: Path) -> None:
    path = tmp_path / "jobs.db"
    store = JobStore(path)
    running = await store.create("m", "make", "a.gcode", 10)
    await store.update(running.id, lines_sent=7, lines_acked=5)
    paused = await store.create("m", "make", "b.gcode", 10)
    await store.update(paused.id, state="paused")
    done = await store.create("m", "make", "c.gcode", 10)
    await store.update(done.id, state="completed")
    store.close()  # as if the daemon died here

    store = JobStore(path)
    recovered = await store.recover()
    assert {j.id for j in recovered} == {running.id, paused.id}
    first = await store.get(running.id)
    assert first is not None
    assert (first.state, first.lines_acked, first.lines_sent) == ("interrupted", 5, 7)
    assert first.ended_at is not None and first.error is not None
    done_again = await store.get(done.id)
    assert done_again is not None and done_again.state == "completed"
    assert await store.recover() == []
    store.close()


async def test_ids_are_never_reused(tmp_path: Path) -> None:
    path = tmp_path / "jobs.db"
    store = JobStore(path)
    first = await store.create("m", "jog", None, None)
    store._db.execute("DELETE FROM jobs")
    store.close()
    store = JobStore(path)
    second = await store.create("m", "jog", None, None)
    assert second.id > first.id
    store.close()


async def test_missing_job_is_none(tmp_path: Path) -> None:
    store = JobStore(tmp_path / "jobs.db")
    assert await store.get(42) is None
    with pytest.raises(KeyError):
        await store.update(42, state="failed")
    store.close()


async def test_a_database_of_an_older_hostd_gains_the_new_columns_and_keeps_its_rows(
    tmp_path: Path,
) -> None:
    path = tmp_path / "jobs.db"
    old = sqlite3.connect(path)
    old.executescript(
        "CREATE TABLE jobs (id INTEGER PRIMARY KEY AUTOINCREMENT, machine TEXT NOT NULL, "
        "file TEXT, kind TEXT NOT NULL, state TEXT NOT NULL, lines_total INTEGER, "
        "lines_sent INTEGER NOT NULL DEFAULT 0, lines_acked INTEGER NOT NULL DEFAULT 0, "
        "started_at TEXT, ended_at TEXT, error_code INTEGER, error_message TEXT);"
        "INSERT INTO jobs (machine, file, kind, state, lines_total, lines_sent, lines_acked) "
        "VALUES ('m1', 'a.nc', 'make', 'interrupted', 50, 40, 30);"
    )
    old.commit()
    old.close()
    store = JobStore(path)
    kept = await store.get(1)
    assert kept is not None and (kept.lines_acked, kept.state) == (30, "interrupted")
    assert kept.line_executed is None and kept.preamble is None  # not known, not zero
    job = await store.create("m1", "make", "a.nc", 10, start_line=25, preamble=["G21", "M3"])
    job = await store.update(job.id, line_executed=27)
    assert (job.line_executed, job.start_line, job.preamble) == (27, 25, ["G21", "M3"])
    assert kept.tool_changes == [] and job.tool_changes == []  # none made
    store.close()


async def test_a_database_before_tool_changes_keeps_its_rows_and_records_them(
    tmp_path: Path,
) -> None:
    """Issue 29's column: added to a database that has every column but it."""
    path = tmp_path / "jobs.db"
    old = sqlite3.connect(path)
    old.executescript(
        "CREATE TABLE jobs (id INTEGER PRIMARY KEY AUTOINCREMENT, machine TEXT NOT NULL, "
        "file TEXT, kind TEXT NOT NULL, state TEXT NOT NULL, lines_total INTEGER, "
        "lines_sent INTEGER NOT NULL DEFAULT 0, lines_acked INTEGER NOT NULL DEFAULT 0, "
        "started_at TEXT, ended_at TEXT, error_code INTEGER, error_message TEXT, "
        "line_executed INTEGER, start_line INTEGER, preamble TEXT);"
        "INSERT INTO jobs (machine, file, kind, state, lines_total, line_executed) "
        "VALUES ('m1', 'a.nc', 'make', 'completed', 50, 50);"
    )
    old.commit()
    old.close()
    store = JobStore(path)
    kept = await store.get(1)
    assert kept is not None and kept.line_executed == 50 and kept.tool_changes == []
    change = ToolChange(tool=2, line=57, at="2026-11-27T10:00:00.000Z")
    job = await store.update(1, tool_changes=[change])
    assert job.tool_changes == [change]
    store.close()
    again = JobStore(path)  # and it opens again, as is
    assert (await again.get(1)) == job
    again.close()
