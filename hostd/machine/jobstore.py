"""Job history in SQLite: one row per job, in `state_dir`, surviving any crash.

The standard library's sqlite3, off the event loop (`asyncio.to_thread`),
one connection behind a lock. WAL mode with synchronous=NORMAL: a committed
row survives a killed daemon (the WAL is on disk; only a power cut may lose
the last commits). Ids come from AUTOINCREMENT, so an id is never reused for
the life of the state directory, even after rows are deleted.

A row's `lines_acked` is written by the job runner as progress is made (see
`hostd.machine.jobs` for how often); it is never more than the controller
answered, because it is only ever copied from the engine's count.
`line_executed` (issue 14) is written with it: the file line the board last
said it was executing, a lower bound (hostd.machine.stream). A resumed job
keeps its `start_line` and the `preamble` it sent before that line.

Columns added after the first release are added to an existing database by
`_migrate` (ALTER TABLE ... ADD COLUMN): old rows keep every value, and read
NULL, i.e. not known, for the new ones.
"""

from __future__ import annotations

import asyncio
import json
import sqlite3
import threading
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel

JobKind = Literal["make", "jog", "settings"]
JobState = Literal["running", "paused", "completed", "failed", "cancelled", "interrupted"]
ACTIVE_STATES = ("running", "paused")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    machine TEXT NOT NULL,
    file TEXT,
    kind TEXT NOT NULL,
    state TEXT NOT NULL,
    lines_total INTEGER,
    lines_sent INTEGER NOT NULL DEFAULT 0,
    lines_acked INTEGER NOT NULL DEFAULT 0,
    started_at TEXT,
    ended_at TEXT,
    error_code INTEGER,
    error_message TEXT,
    line_executed INTEGER,
    start_line INTEGER,
    preamble TEXT,
    tool_changes TEXT
);
CREATE INDEX IF NOT EXISTS jobs_machine ON jobs (machine, id);
"""
# Added after the first schema, with their SQL types: `_migrate` adds the missing ones.
_ADDED = (
    ("line_executed", "INTEGER"),
    ("start_line", "INTEGER"),
    ("preamble", "TEXT"),
    ("tool_changes", "TEXT"),  # issue 29: JSON, [{"tool", "line", "at"}]
    ("file_sha256", "TEXT"),  # the bytes a make job streamed (2026-11-29)
)
_COLUMNS = (
    "id, machine, file, kind, state, lines_total, lines_sent, lines_acked, "
    "started_at, ended_at, error_code, error_message, line_executed, start_line, preamble, "
    "tool_changes, file_sha256"
)


class JobError(BaseModel):
    code: int
    message: str


class ToolChange(BaseModel):
    """One tool change a job made: the tool, the file line of its M6, when it was done."""

    tool: int | None
    line: int
    at: str


class Job(BaseModel):
    """The api.md job object."""

    id: int
    machine: str
    file: str | None
    kind: JobKind
    state: JobState
    lines_total: int | None
    lines_sent: int
    lines_acked: int
    started_at: str | None
    ended_at: str | None
    error: JobError | None
    line_executed: int | None = None  # the file line the board last said it was running
    start_line: int | None = None  # a resumed job's first file line
    preamble: list[str] | None = None  # what a resumed job sent before it
    tool_changes: list[ToolChange] = []  # each tool change the operator made, in order
    # A make job's file as it streamed it, its SHA-256 in hex: a resume of the job must
    # find these bytes (resumes.py). None for other jobs and rows from before 2026-11-29.
    file_sha256: str | None = None

    @classmethod
    def from_row(cls, row: tuple[Any, ...]) -> Job:
        (id_, machine, file, kind, state, total, sent, acked, start, end, code, msg) = row[:12]
        executed, start_line, preamble, changes, sha256 = row[12:17]
        error = JobError(code=code, message=msg or "") if code is not None else None
        return cls(
            id=id_,
            machine=machine,
            file=file,
            kind=kind,
            state=state,
            lines_total=total,
            lines_sent=sent,
            lines_acked=acked,
            started_at=start,
            ended_at=end,
            error=error,
            line_executed=executed,
            start_line=start_line,
            preamble=json.loads(preamble) if preamble else None,
            tool_changes=json.loads(changes) if changes else [],
            file_sha256=sha256,
        )


def now() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


class JobStore:
    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self._lock = threading.Lock()
        with self._lock:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.executescript(_SCHEMA)
            self._migrate()

    def _migrate(self) -> None:
        """Add the columns a database made by an older hostd lacks; its rows are kept."""
        have = {row[1] for row in self._db.execute("PRAGMA table_info(jobs)")}
        for name, kind in _ADDED:
            if name not in have:
                self._db.execute(f"ALTER TABLE jobs ADD COLUMN {name} {kind}")

    def close(self) -> None:
        with self._lock:
            self._db.close()

    # Each public coroutine runs its statement in a worker thread.

    async def recover(self) -> list[Job]:
        """Rows a dead daemon left running or paused become `interrupted`; returns them."""
        return await asyncio.to_thread(self._recover)

    async def create(
        self,
        machine: str,
        kind: JobKind,
        file: str | None,
        lines_total: int | None,
        *,
        start_line: int | None = None,
        preamble: list[str] | None = None,
        file_sha256: str | None = None,
    ) -> Job:
        return await asyncio.to_thread(
            self._create, machine, kind, file, lines_total, start_line, preamble, file_sha256
        )

    async def update(self, job_id: int, **fields: Any) -> Job:
        return await asyncio.to_thread(self._update, job_id, fields)

    async def write(self, job_id: int, **fields: Any) -> None:
        """`update` without reading the row back: a running job's progress, many a second."""
        await asyncio.to_thread(self._set, job_id, fields)

    async def get(self, job_id: int) -> Job | None:
        return await asyncio.to_thread(self._get, job_id)

    async def list_jobs(self, machine: str | None = None, limit: int = 50) -> list[Job]:
        return await asyncio.to_thread(self._list, machine, limit)

    # The blocking halves.

    def _recover(self) -> list[Job]:
        """The rows as they are on disk once ended: end time and error included."""
        with self._lock:
            ids = [
                row[0]
                for row in self._db.execute(
                    "SELECT id FROM jobs WHERE state IN (?, ?)", ACTIVE_STATES
                ).fetchall()
            ]
            self._db.execute(
                "UPDATE jobs SET state = 'interrupted', ended_at = ?, "
                "error_code = COALESCE(error_code, 1002), "
                "error_message = COALESCE(error_message, 'the daemon stopped during the job') "
                "WHERE state IN (?, ?)",
                (now(), *ACTIVE_STATES),
            )
        return [job for job_id in ids if (job := self._get(job_id)) is not None]

    def _create(
        self,
        machine: str,
        kind: str,
        file: str | None,
        total: int | None,
        start_line: int | None,
        preamble: list[str] | None,
        file_sha256: str | None,
    ) -> Job:
        with self._lock:
            cur = self._db.execute(
                "INSERT INTO jobs (machine, file, kind, state, lines_total, started_at, "
                "start_line, preamble, file_sha256) VALUES (?, ?, ?, 'running', ?, ?, ?, ?, ?)",
                (
                    machine,
                    file,
                    kind,
                    total,
                    now(),
                    start_line,
                    None if preamble is None else json.dumps(preamble),
                    file_sha256,
                ),
            )
            job_id = cur.lastrowid
        job = self._get(int(job_id or 0))
        assert job is not None
        return job

    def _update(self, job_id: int, fields: dict[str, Any]) -> Job:
        self._set(job_id, fields)
        job = self._get(job_id)
        if job is None:
            raise KeyError(job_id)
        return job

    def _set(self, job_id: int, fields: dict[str, Any]) -> None:
        error = fields.pop("error", None)
        if isinstance(error, JobError):
            fields["error_code"], fields["error_message"] = error.code, error.message
        if "tool_changes" in fields:
            fields["tool_changes"] = json.dumps(
                [c.model_dump() if isinstance(c, ToolChange) else c for c in fields["tool_changes"]]
            )
        names = ", ".join(f"{name} = ?" for name in fields)
        if names:
            with self._lock:
                self._db.execute(
                    f"UPDATE jobs SET {names} WHERE id = ?", (*fields.values(), job_id)
                )

    def _get(self, job_id: int) -> Job | None:
        with self._lock:
            row = self._db.execute(
                f"SELECT {_COLUMNS} FROM jobs WHERE id = ?", (job_id,)
            ).fetchone()
        return Job.from_row(row) if row else None

    def _list(self, machine: str | None, limit: int) -> list[Job]:
        query = f"SELECT {_COLUMNS} FROM jobs"
        args: tuple[Any, ...] = ()
        if machine is not None:
            query += " WHERE machine = ?"
            args = (machine,)
        query += " ORDER BY id DESC LIMIT ?"
        with self._lock:
            rows = self._db.execute(query, (*args, limit)).fetchall()
        return [Job.from_row(r) for r in rows]
