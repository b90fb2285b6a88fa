"""Uploads on a real file system: own staging, idempotent retries, failures, expiry, quota.

Through `JobsDir`, as the API calls it; what only the daemon can show (two
clients, a restart, the socket's error codes) is in tests/daemon/test_uploads.py.
"""

from __future__ import annotations

import errno
import os
import types
from collections.abc import Callable
from pathlib import Path

import pytest

from hostd.api import uploads
from hostd.api.files import JobsDir, NoSuchFileError
from hostd.api.uploads import ChunkError, NoSuchUpload, StorageError


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def jobs(tmp_path: Path, clock: Clock) -> JobsDir:
    (tmp_path / "jobs").mkdir()
    return JobsDir(tmp_path / "jobs", expiry=60.0, clock=clock)


def staged(jobs: JobsDir) -> dict[str, bytes]:
    staging = jobs.path / ".staging"
    return {p.name: p.read_bytes() for p in staging.iterdir()} if staging.exists() else {}


def start(jobs: JobsDir, name: str, data: bytes) -> str:
    upload = jobs.upload(name, data, final=False).upload
    assert upload is not None
    return upload


def test_chunks_stay_hidden_until_the_final_one(jobs: JobsDir) -> None:
    first = jobs.upload("big.gcode", b"G0 X1\n", final=False)
    assert first.size == 6 and first.upload is not None
    upload = first.upload
    second = jobs.upload("big.gcode", b"G0 X2\n", upload_id=upload, offset=6, final=False)
    assert (second.size, second.upload) == (12, upload)
    assert jobs.entries() == []  # nothing half-uploaded to start
    with pytest.raises(NoSuchFileError):
        jobs.resolve("big.gcode")

    done = jobs.upload("big.gcode", b"G0 X3\n", upload_id=upload, offset=12)

    assert (done.size, done.upload) == (18, None)
    assert (jobs.path / "big.gcode").read_bytes() == b"G0 X1\nG0 X2\nG0 X3\n"
    assert staged(jobs) == {}


def test_upload_ids_are_random_and_each_has_its_own_staging(jobs: JobsDir) -> None:
    ids = {start(jobs, "a.gcode", b"G0\n") for _ in range(20)}
    assert len(ids) == 20
    assert all(len(i) == 32 and int(i, 16) >= 0 for i in ids)
    assert set(staged(jobs)) == ids


def test_an_append_by_name_continues_only_the_version_its_client_published(
    jobs: JobsDir,
) -> None:
    """api.md's chunks: `append: true` alone continues what that connection published."""
    first = jobs.upload("a.gcode", b"G0 X1\n")
    assert first.version is not None

    second = jobs.upload("a.gcode", b"G0 X2\n", append=True, by_name=True, after=first.version)

    assert (second.size, second.upload) == (12, None)
    assert (jobs.path / "a.gcode").read_bytes() == b"G0 X1\nG0 X2\n"
    assert second.version is not None and second.version[1] != first.version[1]  # a new file
    with pytest.raises(ChunkError, match="replaced by another upload") as stale:
        jobs.upload("a.gcode", b"G0 X3\n", append=True, by_name=True, after=first.version)
    assert stale.value.expected == 12
    assert (jobs.path / "a.gcode").read_bytes() == b"G0 X1\nG0 X2\n"
    assert staged(jobs) == {}


def test_an_append_by_name_tells_a_reused_inode_from_its_own_file(jobs: JobsDir) -> None:
    """A file system may give a freed inode to the next file: the write time tells them apart."""
    first = jobs.upload("a.gcode", b"G0 X1\n").version
    assert first is not None
    dev, ino, size, written = first
    other_file_same_inode = (dev, ino, size, written - 1)

    with pytest.raises(ChunkError, match="replaced by another upload"):
        jobs.upload("a.gcode", b"G0 X2\n", append=True, by_name=True, after=other_file_same_inode)

    assert (jobs.path / "a.gcode").read_bytes() == b"G0 X1\n"


def test_an_append_by_name_without_a_version_of_its_own_is_refused(jobs: JobsDir) -> None:
    jobs.upload("a.gcode", b"old\n")
    jobs.upload("a.gcode", b"G0 X1\n", final=False)  # another upload, still open

    with pytest.raises(ChunkError, match="it uploaded none") as refused:
        jobs.upload("a.gcode", b"G0 X2\n", append=True, by_name=True)

    assert refused.value.expected == 4 and "give `offset` 4" in str(refused.value)
    assert (jobs.path / "a.gcode").read_bytes() == b"old\n"
    gone = jobs.upload("b.gcode", b"G0\n").version
    jobs.delete("b.gcode")
    with pytest.raises(ChunkError, match="was deleted"):
        jobs.upload("b.gcode", b"G1\n", append=True, by_name=True, after=gone)
    assert not (jobs.path / "b.gcode").exists()


def test_an_append_without_an_offset_by_a_caller_that_keeps_no_versions_is_refused(
    jobs: JobsDir,
) -> None:
    """JobsDir itself does not guess: `append` alone, not by name, still needs `offset`."""
    jobs.upload("a.gcode", b"old\n")
    with pytest.raises(ChunkError, match="needs offset 4") as refused:
        jobs.upload("a.gcode", b"G0 X2\n", append=True)
    assert refused.value.expected == 4


def test_append_to_a_published_file_names_its_size(jobs: JobsDir) -> None:
    jobs.upload("a.gcode", b"G0 X1\n")
    with pytest.raises(ChunkError):
        jobs.upload("a.gcode", b"G0 X2\n", append=True, offset=5)

    assert jobs.upload("a.gcode", b"G0 X2\n", append=True, offset=6).size == 12
    assert (jobs.path / "a.gcode").read_bytes() == b"G0 X1\nG0 X2\n"
    assert jobs.upload("new.gcode", b"G0\n", append=True, offset=0).size == 3


def test_a_retried_chunk_changes_nothing(jobs: JobsDir) -> None:
    upload = start(jobs, "a.gcode", b"one\n")
    jobs.upload("a.gcode", b"two\n", upload_id=upload, offset=4, final=False)

    again = jobs.upload("a.gcode", b"two\n", upload_id=upload, offset=4, final=False)
    earlier = jobs.upload("a.gcode", b"one\n", upload_id=upload, offset=0, final=False)

    assert again.size == earlier.size == 8
    assert staged(jobs) == {upload: b"one\ntwo\n"}
    jobs.upload("a.gcode", b"three\n", upload_id=upload, offset=8)
    assert (jobs.path / "a.gcode").read_bytes() == b"one\ntwo\nthree\n"


@pytest.mark.parametrize(
    ("data", "offset", "final"),
    [
        (b"TWO\n", 4, False),  # a "retry" with other bytes
        (b"two\nmore", 4, False),  # overlaps the end
        (b"x", 9, False),  # leaves a gap
        (b"ne", 1, True),  # repeats staged bytes, but cannot end the file there
    ],
)
def test_a_chunk_that_does_not_continue_the_upload_is_refused_with_the_expected_offset(
    jobs: JobsDir, data: bytes, offset: int, final: bool
) -> None:
    upload = start(jobs, "a.gcode", b"one\n")
    jobs.upload("a.gcode", b"two\n", upload_id=upload, offset=4, final=False)
    with pytest.raises(ChunkError, match="expected offset 8") as refused:
        jobs.upload("a.gcode", data, upload_id=upload, offset=offset, final=final)
    assert refused.value.expected == 8
    assert staged(jobs) == {upload: b"one\ntwo\n"}
    assert jobs.entries() == []


def test_a_chunk_needs_its_offset_and_its_own_name(jobs: JobsDir) -> None:
    upload = start(jobs, "a.gcode", b"one\n")
    with pytest.raises(ChunkError, match="needs `offset`"):
        jobs.upload("a.gcode", b"two\n", upload_id=upload, final=False)
    with pytest.raises(ChunkError, match=r"is for 'a\.gcode'"):
        jobs.upload("b.gcode", b"two\n", upload_id=upload, offset=4)
    with pytest.raises(ChunkError, match="starts at offset 0"):
        jobs.upload("c.gcode", b"two\n", offset=4)
    assert staged(jobs) == {upload: b"one\n"} and jobs.entries() == []


def test_a_retried_final_chunk_gets_the_same_answer_and_nothing_else_does(jobs: JobsDir) -> None:
    upload = start(jobs, "a.gcode", b"one\n")
    done = jobs.upload("a.gcode", b"two\n", upload_id=upload, offset=4)
    jobs.upload("a.gcode", b"newer\n")  # someone else publishes after

    assert jobs.upload("a.gcode", b"two\n", upload_id=upload, offset=4) == done
    assert (jobs.path / "a.gcode").read_bytes() == b"newer\n"
    for data, offset, final in ((b"two\n", 4, False), (b"TWO\n", 4, True), (b"x", 8, True)):
        with pytest.raises(NoSuchUpload, match="is finished"):
            jobs.upload("a.gcode", data, upload_id=upload, offset=offset, final=final)
    assert (jobs.path / "a.gcode").read_bytes() == b"newer\n"


def test_an_unknown_upload_id_is_a_clear_error(jobs: JobsDir) -> None:
    with pytest.raises(NoSuchUpload, match="start the upload again"):
        jobs.upload("a.gcode", b"x", upload_id="0" * 32, offset=0)


def test_two_uploads_of_one_name_never_mix(jobs: JobsDir) -> None:
    a = start(jobs, "part.gcode", b"A1\n")
    b = start(jobs, "part.gcode", b"B1\n")
    jobs.upload("part.gcode", b"A2\n", upload_id=a, offset=3, final=False)
    jobs.upload("part.gcode", b"B2\n", upload_id=b, offset=3, final=False)

    jobs.upload("part.gcode", b"A3\n", upload_id=a, offset=6)
    assert (jobs.path / "part.gcode").read_bytes() == b"A1\nA2\nA3\n"
    jobs.upload("part.gcode", b"B3\n", upload_id=b, offset=6)
    assert (jobs.path / "part.gcode").read_bytes() == b"B1\nB2\nB3\n"


# -- failures ----------------------------------------------------------------


def uploads_os(monkeypatch: pytest.MonkeyPatch) -> types.SimpleNamespace:
    """uploads.py's own `os`, a copy of the module's names, to patch: patching `os`
    itself would fail every `os.write` of the process, a multiprocessing finalizer's
    run by the garbage collector meanwhile among them (an error in another test)."""
    own = uploads.os
    if not isinstance(own, types.SimpleNamespace):
        own = types.SimpleNamespace(**vars(os))
        monkeypatch.setattr(uploads, "os", own)
    return own


def failing_write(monkeypatch: pytest.MonkeyPatch, after: int) -> list[int]:
    """`os.write` in uploads.py writes `after` bytes of the next chunk, then the disk is full."""
    real = os.write
    calls: list[int] = []

    def write(fd: int, data: bytes | memoryview) -> int:
        calls.append(len(data))
        if len(calls) == 1 and after:
            return real(fd, bytes(data[:after]))
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(uploads_os(monkeypatch), "write", write)
    return calls


def test_a_full_disk_leaves_staging_as_it_was_and_the_same_chunk_then_succeeds(
    jobs: JobsDir, monkeypatch: pytest.MonkeyPatch
) -> None:
    jobs.upload("a.gcode", b"old\n")
    upload = start(jobs, "a.gcode", b"G0 X1\n")
    with monkeypatch.context() as patch:
        calls = failing_write(patch, after=3)  # a partial write, then ENOSPC
        with pytest.raises(StorageError, match="no space left on device") as refused:
            jobs.upload("a.gcode", b"G0 X2\n", upload_id=upload, offset=6, final=False)
    assert len(calls) == 2
    assert refused.value.reason == "full"
    assert "nothing of it was kept" in refused.value.message
    assert staged(jobs) == {upload: b"G0 X1\n"}
    assert (jobs.path / "a.gcode").read_bytes() == b"old\n"

    jobs.upload("a.gcode", b"G0 X2\n", upload_id=upload, offset=6)

    assert (jobs.path / "a.gcode").read_bytes() == b"G0 X1\nG0 X2\n"


def test_a_whole_file_that_does_not_fit_leaves_nothing(
    jobs: JobsDir, monkeypatch: pytest.MonkeyPatch
) -> None:
    with monkeypatch.context() as patch:
        failing_write(patch, after=0)
        with pytest.raises(StorageError, match="no space left on device"):
            jobs.upload("a.gcode", b"G0 X1\n")
    assert staged(jobs) == {} and jobs.entries() == []


def test_staging_that_cannot_be_cut_back_discards_the_upload(
    jobs: JobsDir, monkeypatch: pytest.MonkeyPatch
) -> None:
    upload = start(jobs, "a.gcode", b"G0 X1\n")
    with monkeypatch.context() as patch:
        failing_write(patch, after=2)
        patch.setattr(uploads_os(patch), "ftruncate", _raise(errno.EIO))
        assert os.write is not uploads.os.write  # the process's own still writes
        with pytest.raises(StorageError, match="upload is discarded"):
            jobs.upload("a.gcode", b"G0 X2\n", upload_id=upload, offset=6)
    assert staged(jobs) == {} and jobs.entries() == []
    with pytest.raises(NoSuchUpload):
        jobs.upload("a.gcode", b"G0 X2\n", upload_id=upload, offset=6)


def test_a_final_flush_that_fails_publishes_nothing(
    jobs: JobsDir, monkeypatch: pytest.MonkeyPatch
) -> None:
    jobs.upload("a.gcode", b"old\n")
    upload = start(jobs, "a.gcode", b"G0 X1\n")
    with monkeypatch.context() as patch:
        patch.setattr(uploads_os(patch), "fsync", _raise(errno.EIO))
        with pytest.raises(StorageError, match="cannot flush the upload") as refused:
            jobs.upload("a.gcode", b"G0 X2\n", upload_id=upload, offset=6)
    assert refused.value.reason == "io"
    assert (jobs.path / "a.gcode").read_bytes() == b"old\n"
    assert staged(jobs) == {}


def _raise(code: int) -> Callable[..., None]:
    def fail(*args: object) -> None:
        raise OSError(code, os.strerror(code))

    return fail


# -- links -------------------------------------------------------------------


def test_a_link_planted_at_the_staging_path_is_not_followed(jobs: JobsDir, tmp_path: Path) -> None:
    secret = tmp_path / "secret"
    secret.write_bytes(b"G0 X1\n")  # even the same bytes: it is not the upload's file
    upload = start(jobs, "a.gcode", b"G0 X1\n")
    staging = jobs.path / ".staging" / upload
    staging.unlink()
    staging.symlink_to(secret)

    with pytest.raises(StorageError, match="is gone or is a link"):
        jobs.upload("a.gcode", b"G0 X2\n", upload_id=upload, offset=6)

    assert secret.read_bytes() == b"G0 X1\n"
    assert jobs.entries() == [] and staged(jobs) == {}
    with pytest.raises(NoSuchUpload):
        jobs.upload("a.gcode", b"G0 X2\n", upload_id=upload, offset=6)


def test_staging_replaced_by_another_file_is_not_used(jobs: JobsDir, tmp_path: Path) -> None:
    upload = start(jobs, "a.gcode", b"G0 X1\n")
    staging = jobs.path / ".staging" / upload
    other = jobs.path / ".staging" / "other"
    other.write_bytes(b"G0 X1\n")  # same bytes, another file, put in its place
    other.replace(staging)

    with pytest.raises(StorageError, match="changed by something else"):
        jobs.upload("a.gcode", b"G0 X2\n", upload_id=upload, offset=6)
    assert jobs.entries() == [] and staged(jobs) == {}


def test_a_new_staging_file_is_never_opened_through_a_planted_link(
    jobs: JobsDir, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    secret = tmp_path / "secret"
    secret.write_bytes(b"keep\n")

    def plant(nbytes: int) -> str:
        """The id is drawn, and someone wins the race to its path with a link."""
        (jobs.path / ".staging" / ("a" * 32)).symlink_to(secret)
        return "a" * 32

    monkeypatch.setattr(uploads.secrets, "token_hex", plant)

    with pytest.raises(StorageError, match="file exists"):
        jobs.upload("a.gcode", b"G0\n")

    assert secret.read_bytes() == b"keep\n" and jobs.entries() == []


def test_a_link_left_in_staging_is_removed_not_followed(jobs: JobsDir, tmp_path: Path) -> None:
    secret = tmp_path / "secret"
    secret.write_bytes(b"keep\n")
    (jobs.path / ".staging").mkdir()
    (jobs.path / ".staging" / "stray").symlink_to(secret)

    start(jobs, "a.gcode", b"G0\n")

    assert secret.read_bytes() == b"keep\n"
    assert not (jobs.path / ".staging" / "stray").is_symlink()


def test_a_link_in_place_of_the_staging_directory_is_replaced_not_followed(
    jobs: JobsDir, tmp_path: Path
) -> None:
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (jobs.path / ".staging").symlink_to(elsewhere)

    upload = start(jobs, "a.gcode", b"G0\n")

    assert os.listdir(elsewhere) == []
    assert not (jobs.path / ".staging").is_symlink()
    assert staged(jobs) == {upload: b"G0\n"}


# -- restart, expiry ---------------------------------------------------------


def test_a_restart_mid_upload_publishes_nothing(jobs: JobsDir, clock: Clock) -> None:
    jobs.upload("a.gcode", b"old\n")
    upload = start(jobs, "a.gcode", b"G0 X1\n")

    after = JobsDir(jobs.path, clock=clock)  # the next daemon on the same directory
    assert after.clean() == [upload]

    with pytest.raises(NoSuchUpload, match="restarted"):
        after.upload("a.gcode", b"G0 X2\n", upload_id=upload, offset=6)
    assert (jobs.path / "a.gcode").read_bytes() == b"old\n"
    assert staged(after) == {}


def test_staging_nobody_owns_goes_with_the_next_upload(jobs: JobsDir, clock: Clock) -> None:
    """Even without the start-up clean, what an earlier daemon left is never used."""
    upload = start(jobs, "a.gcode", b"G0 X1\n")
    after = JobsDir(jobs.path, clock=clock)

    mine = start(after, "b.gcode", b"G0\n")

    assert staged(after) == {mine: b"G0\n"}
    with pytest.raises(NoSuchUpload):
        after.upload("a.gcode", b"G0 X2\n", upload_id=upload, offset=6)


def test_an_abandoned_upload_expires(jobs: JobsDir, clock: Clock) -> None:
    upload = start(jobs, "a.gcode", b"G0 X1\n")
    clock.now += 59
    jobs.upload("a.gcode", b"G0 X2\n", upload_id=upload, offset=6, final=False)
    clock.now += 59  # a chunk keeps it alive
    assert jobs.uploads.expire() == []
    clock.now += 1

    assert jobs.uploads.expire() == [upload]

    assert staged(jobs) == {}
    with pytest.raises(NoSuchUpload, match="expired"):
        jobs.upload("a.gcode", b"G0 X3\n", upload_id=upload, offset=12)
    assert jobs.entries() == []


def test_expired_uploads_go_before_the_next_call_is_served(jobs: JobsDir, clock: Clock) -> None:
    old = start(jobs, "a.gcode", b"G0 X1\n")
    clock.now += 60
    new = start(jobs, "b.gcode", b"G0\n")
    assert staged(jobs) == {new: b"G0\n"}
    with pytest.raises(NoSuchUpload):
        jobs.upload("a.gcode", b"G0 X2\n", upload_id=old, offset=6)


# -- quota -------------------------------------------------------------------


def test_the_quota_counts_published_files_and_staging(tmp_path: Path) -> None:
    (tmp_path / "jobs").mkdir()
    jobs = JobsDir(tmp_path / "jobs", quota=20)
    jobs.upload("a.gcode", b"0123456789")  # 10 published
    upload = start(jobs, "b.gcode", b"01234")  # 5 staged

    with pytest.raises(StorageError, match="quota of 20 bytes") as refused:
        jobs.upload("b.gcode", b"012345", upload_id=upload, offset=5, final=False)

    assert refused.value.reason == "quota"
    assert staged(jobs) == {upload: b"01234"}
    jobs.upload("b.gcode", b"01234", upload_id=upload, offset=5)  # exactly 20 fits
    with pytest.raises(StorageError, match="quota"):
        jobs.upload("c.gcode", b"x")
    assert [f.name for f in jobs.entries()] == ["a.gcode", "b.gcode"] and staged(jobs) == {}
    jobs.delete("a.gcode")
    assert jobs.upload("c.gcode", b"x").size == 1


def test_an_append_needs_room_for_the_copy_of_the_file(tmp_path: Path) -> None:
    (tmp_path / "jobs").mkdir()
    jobs = JobsDir(tmp_path / "jobs", quota=25)
    jobs.upload("a.gcode", b"0123456789" * 2)
    with pytest.raises(StorageError, match="quota"):
        jobs.upload("a.gcode", b"x", append=True, offset=20)
    assert staged(jobs) == {}
    assert (jobs.path / "a.gcode").read_bytes() == b"0123456789" * 2
