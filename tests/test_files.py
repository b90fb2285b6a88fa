"""The jobs directory: names that cannot escape it, atomic writes, listing and deleting.

How uploads stage, retry, fail and expire: tests/test_uploads.py.
"""

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
    assert jobs.upload("a.gcode", b"G0 X1\n").size == 6
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
    assert sorted(os.listdir(jobs.path)) == [".staging", "a.gcode"]
    assert os.listdir(jobs.path / ".staging") == []


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


def test_clean_removes_what_unfinished_uploads_left(jobs: JobsDir) -> None:
    jobs.upload("a.gcode", b"G0\n")
    upload = jobs.upload("b.gcode", b"G0\n", final=False).upload
    (jobs.path / ".tmp-abc").write_bytes(b"x")  # what older versions left
    (jobs.path / ".c.gcode.upload").write_bytes(b"x")
    assert sorted(jobs.clean()) == sorted([upload, ".c.gcode.upload", ".tmp-abc"])
    assert sorted(os.listdir(jobs.path)) == [".staging", "a.gcode"]
    assert os.listdir(jobs.path / ".staging") == []
