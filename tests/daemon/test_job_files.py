"""A job file is read as what the API checked it to be: a regular file of the jobs
directory. A link or a FIFO put in its place after the check is refused where the file
is opened (hostd/machine/jobfile.py), never followed or waited on."""

from __future__ import annotations

import asyncio
import hashlib
import os
import sqlite3
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar, cast

import pytest

from hostd.machine import jobstart, preflight, resumes
from hostd.machine.jobfile import FileChanged, NoSuchFile, open_binary, open_text, version_of
from hostd.machine.workers import WorkerPool
from hostd.protocol import dialects
from tests.daemon.conftest import Rpc, Running, running_daemon
from tests.daemon.test_api import fails

pytestmark = pytest.mark.asyncio
T = TypeVar("T")

# What a job directory's writer must not get the daemon to read for it.
SECRET = "G0 X123.456 (a file outside the jobs directory)\n"


def outside(tmp_path: Path) -> Path:
    secret = tmp_path / "outside.nc"
    secret.write_text(SECRET)
    return secret


async def test_a_regular_file_opens_and_reads_whole(tmp_path: Path) -> None:
    path = tmp_path / "a.nc"
    path.write_bytes(b"G0 X1\nG1 \xff Y2\n")
    with open_binary(path) as f:
        assert f.read() == b"G0 X1\nG1 \xff Y2\n"
    with open_text(path) as f:  # as a job's lines are read: an undecodable byte replaced
        assert f.read() == "G0 X1\nG1 \ufffd Y2\n"


async def test_a_link_a_directory_or_nothing_is_no_job_file(tmp_path: Path) -> None:
    link = tmp_path / "link.nc"
    link.symlink_to(outside(tmp_path))
    (tmp_path / "dir.nc").mkdir()
    for name, says in (
        ("link.nc", "'link.nc' is not a regular file (a link)"),
        ("dir.nc", "'dir.nc' is not a regular file"),
        ("gone.nc", "no file 'gone.nc' in the jobs directory"),
    ):
        with pytest.raises(NoSuchFile) as refused:
            open_text(tmp_path / name)
        assert refused.value.code == 1004 and refused.value.message == says


async def test_a_fifo_is_refused_at_once_not_waited_on(tmp_path: Path) -> None:
    """A FIFO's open for reading waits for a writer, forever if none comes: in a worker
    thread, that is a thread and a job start lost."""
    fifo = tmp_path / "fifo.nc"
    os.mkfifo(fifo)
    opening = asyncio.create_task(asyncio.to_thread(open_binary, fifo))
    done, _ = await asyncio.wait({opening}, timeout=10)
    if not done:  # unblock the thread before failing, or the test run hangs at its end
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        pytest.fail("the open of a FIFO waited for a writer")
    with pytest.raises(NoSuchFile, match="is not a regular file"):
        opening.result()


async def test_a_link_swapped_in_after_the_check_is_not_streamed(
    hostd: Running, rpc: Rpc, tmp_path: Path
) -> None:
    """`job.start` checks the name; the machine opens it afterwards. A link put there in
    between is refused where the machine opens it: nothing of its target goes out."""
    (hostd.jobs / "swapped.nc").symlink_to(outside(tmp_path))
    machine = hostd.api.machine("sim1")
    with pytest.raises(NoSuchFile, match="a link"):
        await machine.start_make("swapped.nc")
    status = await rpc.call("machine.status", machine="sim1")
    assert status["supervisor"] == "idle" and status["job"] is None
    assert await rpc.call("job.list", machine="sim1") == []


async def test_a_recovery_never_plans_from_a_link_put_in_the_files_place(tmp_path: Path) -> None:
    """`job.recovery` of a job by its id reads the file the job ran, by its name: with a
    link in its place now there is no safe resume (1011), not a plan of the link's
    target."""
    async with running_daemon(tmp_path, safe_z=0.0) as hostd:
        rpc = await hostd.client()
        try:
            await hostd.idle(rpc)
            await _recovery_refuses_a_link(hostd, rpc, tmp_path)
        finally:
            await rpc.close()


async def _recovery_refuses_a_link(hostd: Running, rpc: Rpc, tmp_path: Path) -> None:
    program = "G21 G90\nG0 X0 Y0 Z5\n" + "".join(f"G1 X{i % 30} Y1 Z5 F1200\n" for i in range(400))
    await rpc.call("file.upload", name="long.nc", data=program)
    await rpc.call("subscribe", topics=["job"], machine="sim1")
    started = await rpc.call("job.start", machine="sim1", file="long.nc")
    await rpc.notification(
        lambda n: n["method"] == "job" and (n["params"]["job"]["line_executed"] or 0) >= 20, 30
    )
    cancelled = await rpc.call("job.cancel", machine="sim1")
    assert cancelled["state"] == "cancelled" and cancelled["id"] == started["job"]
    plan = await rpc.call("job.recovery", job=started["job"])  # the file as it ran: a plan
    assert plan["job"] == started["job"]

    (hostd.jobs / "long.nc").unlink()
    (hostd.jobs / "long.nc").symlink_to(outside(tmp_path))
    refused = await fails(1011, rpc.call("job.recovery", job=started["job"]))  # no safe resume
    assert "'long.nc' is not a regular file (a link)" in refused.message
    assert "123.456" not in refused.message


async def test_a_version_taken_is_the_one_opened_or_none(tmp_path: Path) -> None:
    path = tmp_path / "a.nc"
    path.write_text("G0 X1\n")
    version = version_of(path)
    with open_text(path, version) as f:
        assert f.read() == "G0 X1\n"
    newer = tmp_path / "b.nc"
    newer.write_text("G0 X1\n")  # the same bytes, another file: another version
    os.replace(newer, path)
    with pytest.raises(FileChanged) as refused:
        open_text(path, version)
    assert refused.value.code == 1004 and "changed while it was being checked" in str(refused.value)


async def test_a_version_uploaded_during_a_start_s_checks_is_never_streamed(
    hostd: Running, rpc: Rpc, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two clients race: one starts `part.nc`, the other uploads a new `part.nc` while the
    first one's checks run. The job streams the version that was checked or nothing; here
    nothing, and the next start checks the new version (which the check refuses: an M6
    on a machine with no tool-change policy)."""
    await rpc.call("file.upload", name="part.nc", data="G21 G90\nG0 X1 Y1\n")
    checked = jobstart.check_file

    async def check_then_upload(*args: Any, **kwargs: Any) -> Any:
        found = await checked(*args, **kwargs)
        other = await hostd.client()  # the second client's upload lands now
        try:
            await other.call("file.upload", name="part.nc", data="G0 X2\nM6 T2\n")
        finally:
            await other.close()
        return found

    monkeypatch.setattr(jobstart, "check_file", check_then_upload)
    refused = await fails(1004, rpc.call("job.start", machine="sim1", file="part.nc"))
    assert "'part.nc' changed while it was being checked" in refused.message
    assert await rpc.call("job.list", machine="sim1") == []
    assert (await rpc.call("machine.status", machine="sim1"))["supervisor"] == "idle"

    monkeypatch.undo()
    again = await fails(1008, rpc.call("job.start", machine="sim1", file="part.nc"))
    assert "line 2" in again.message and "M6" in again.message  # the new version, checked


class _Racing:
    """A worker pool that runs in this process, after another version of `path` is
    published: the moment between what the caller read and what the worker reads."""

    def __init__(self, path: Path, text: str) -> None:
        self.path, self.text = path, text

    async def run(self, what: str, fn: Callable[..., T], *args: Any) -> T:
        newer = self.path.with_name("newer.tmp")
        newer.write_text(self.text)
        os.replace(newer, self.path)  # as an upload publishes
        return fn(*args)


class _Here:
    async def run(self, what: str, fn: Callable[..., T], *args: Any) -> T:
        return fn(*args)


async def test_an_analysis_is_never_kept_under_another_version_s_hash(tmp_path: Path) -> None:
    """The analysis is kept by the file's hash. A version published between the hash and
    the analysis must not be analysed under the first one's hash: the same bytes
    uploaded again would get the other version's bounds, and its travel check."""
    path = tmp_path / "part.nc"
    path.write_text("G21 G90\nG0 X10 Y10\n")
    spec = dialects.lookup("grbl")
    racing = cast(WorkerPool, _Racing(path, "G21 G90\nG0 X900 Y10\n"))
    with pytest.raises(FileChanged):
        await preflight.analyze_file(path, spec, pool=racing)
    path.write_text("G21 G90\nG0 X10 Y10\n")  # the first bytes again
    analysed = await preflight.analyze_file(path, spec, pool=cast(WorkerPool, _Here()))
    assert analysed.analysis.bounds["x"] == (10.0, 10.0)


async def test_a_check_or_a_plan_of_a_start_reads_its_version_or_refuses(tmp_path: Path) -> None:
    path = tmp_path / "part.nc"
    path.write_text("G21 G90\nG0 X10 Y10 Z5\nG1 Z-1 F300\nG1 X20\n")
    version = version_of(path)
    spec = dialects.lookup("grbl")
    with pytest.raises(FileChanged):
        await preflight.check_file(
            path, spec, 128, None, pool=cast(WorkerPool, _Racing(path, "M6 T2\n")), version=version
        )
    path.write_text("G21 G90\nG0 X10 Y10 Z5\nG1 Z-1 F300\nG1 X20\n")
    with pytest.raises(FileChanged):  # 1004 as the start's other checks, not 1011
        await resumes.plan_at(
            path,
            3,
            spec,
            board=None,
            safe_z=5.0,
            dwell=0.0,
            pool=cast(WorkerPool, _Racing(path, "G0 X1\n")),
            version=version_of(path),
        )


async def test_a_resume_of_a_job_must_find_the_bytes_the_job_ran(tmp_path: Path) -> None:
    """A lost job's row keeps the SHA-256 of the file it streamed. Its resume by id plans
    only from those bytes: another program under the same name would be run from the
    middle on this job's workpiece. The same bytes uploaded again resume; a plan by
    machine, file and line is the operator's own choice and is not compared."""
    async with running_daemon(tmp_path, safe_z=0.0) as hostd:
        rpc = await hostd.client()
        try:
            await hostd.idle(rpc)
            await _resume_by_bytes(hostd, rpc)
        finally:
            await rpc.close()


async def _resume_by_bytes(hostd: Running, rpc: Rpc) -> None:
    program = "G21 G90\nG0 X0 Y0 Z5\n" + "".join(f"G1 X{i % 30} Y1 Z5 F1200\n" for i in range(400))
    other = program.replace("Y1 Z5", "Y2 Z5")  # the next part: same lines, another Y
    await rpc.call("file.upload", name="part.nc", data=program)
    await rpc.call("subscribe", topics=["job"], machine="sim1")
    job_id = (await rpc.call("job.start", machine="sim1", file="part.nc"))["job"]
    await rpc.notification(
        lambda n: n["method"] == "job" and (n["params"]["job"]["line_executed"] or 0) >= 20, 30
    )
    await rpc.call("job.cancel", machine="sim1")
    job = await rpc.call("job.get", job=job_id)
    assert job["file_sha256"] == hashlib.sha256(program.encode()).hexdigest()

    await rpc.call("file.upload", name="part.nc", data=other)
    refused = await fails(1011, rpc.call("job.recovery", job=job_id))
    assert f"part.nc is not the file job {job_id} ran: it changed since" in refused.message
    line = (await rpc.call("job.get", job=job_id))["line_executed"]
    chosen = await rpc.call("job.recovery", machine="sim1", file="part.nc", line=line)
    assert chosen["line"] == line  # by file and line: this version, as asked

    await rpc.call("file.upload", name="part.nc", data=program)  # the job's bytes again
    plan = await rpc.call("job.recovery", job=job_id)
    assert plan["line"] == line and not any("not recorded" in u for u in plan["uncertain"])

    # A row an older hostd wrote has no SHA-256: the plan says the file is unchecked.
    store = hostd.daemon.store
    assert store is not None
    with sqlite3.connect(store.path) as db:
        db.execute("UPDATE jobs SET file_sha256 = NULL WHERE id = ?", (job_id,))
    plan = await rpc.call("job.recovery", job=job_id)
    assert any(
        f"which version of part.nc job {job_id} ran was not recorded" in u
        for u in plan["uncertain"]
    )
