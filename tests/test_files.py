"""The jobs directory: names that cannot escape it, atomic writes, chunked uploads."""

from __future__ import annotations

import base64
import os
from pathlib import Path

import pytest

from hostd.api.files import (
    FileNameError,
    InvalidData,
    JobsDir,
    NoSuchFileError,
    check_name,
    decode,
)


@pytest.fixture
def jobs(tmp_path: Path) -> JobsDir:
    (tmp_path / "jobs").mkdir()
    return JobsDir(tmp_path / "jobs")


@pytest.mark.parametrize(
    "name",
    [
        "",
        ".",
        "..",
        "../etc/passwd",
        "/etc/passwd",
        "a/b.gcode",
        "..\\x",
        "a\x00b",
        ".hidden",
        "x" * 201,
        "tab\there",
    ],
)
def test_names_that_could_leave_the_directory_are_refused(name: str) -> None:
    with pytest.raises(FileNameError):
        check_name(name)


def test_plain_names_are_fine() -> None:
    for name in ("part.gcode", "Teil 2 (final).nc", "ü.gcode", "a..b"):
        assert check_name(name) == name


def test_upload_list_delete(jobs: JobsDir) -> None:
    assert jobs.upload("a.gcode", b"G0 X1\n") == 6
    assert [(f.name, f.size) for f in jobs.entries()] == [("a.gcode", 6)]
    assert jobs.entries()[0].modified.endswith("Z")
    jobs.delete("a.gcode")
    assert jobs.entries() == []
    with pytest.raises(NoSuchFileError):
        jobs.delete("a.gcode")


def test_upload_replaces_atomically_and_leaves_no_temp_files(jobs: JobsDir) -> None:
    jobs.upload("a.gcode", b"old\n")
    jobs.upload("a.gcode", b"new\n")
    assert (jobs.path / "a.gcode").read_bytes() == b"new\n"
    assert os.listdir(jobs.path) == ["a.gcode"]


def test_chunks_stay_hidden_until_the_final_one(jobs: JobsDir) -> None:
    jobs.upload("big.gcode", b"G0 X1\n", final=False)
    jobs.upload("big.gcode", b"G0 X2\n", append=True, final=False)
    assert jobs.entries() == []  # nothing half-uploaded to start
    with pytest.raises(NoSuchFileError):
        jobs.resolve("big.gcode")
    assert jobs.upload("big.gcode", b"G0 X3\n", append=True) == 18
    assert (jobs.path / "big.gcode").read_bytes() == b"G0 X1\nG0 X2\nG0 X3\n"
    assert os.listdir(jobs.path) == ["big.gcode"]


def test_append_to_a_published_file(jobs: JobsDir) -> None:
    jobs.upload("a.gcode", b"G0 X1\n")
    jobs.upload("a.gcode", b"G0 X2\n", append=True)
    assert (jobs.path / "a.gcode").read_bytes() == b"G0 X1\nG0 X2\n"


def test_a_symlink_planted_in_the_directory_is_not_followed(jobs: JobsDir, tmp_path: Path) -> None:
    secret = tmp_path / "secret"
    secret.write_text("not for clients")
    (jobs.path / "link.gcode").symlink_to(secret)
    assert jobs.entries() == []
    with pytest.raises(NoSuchFileError):
        jobs.resolve("link.gcode")
    with pytest.raises(NoSuchFileError):
        jobs.delete("link.gcode")
    assert secret.exists()
    jobs.upload("link.gcode", b"G0\n")  # replaces the link itself, not its target
    assert secret.read_text() == "not for clients"


def test_base64_data() -> None:
    assert decode(base64.b64encode(b"\x00\xff").decode(), "base64") == b"\x00\xff"
    with pytest.raises(InvalidData):
        decode("not base64!", "base64")


def test_clean_removes_what_an_unfinished_upload_left(jobs: JobsDir) -> None:
    jobs.upload("a.gcode", b"G0\n")
    jobs.upload("b.gcode", b"G0\n", final=False)
    (jobs.path / ".tmp-abc").write_bytes(b"x")
    assert sorted(jobs.clean()) == [".b.gcode.upload", ".tmp-abc"]
    assert os.listdir(jobs.path) == ["a.gcode"]
