"""A job file opened as what the API checked it to be: a regular file of the jobs
directory, never a link, a FIFO or a device; and, for a job's start, the very version
its checks read.

The API checks a name before anything opens it (`JobsDir.resolve`: `lstat`,
a regular file). The file is opened later, often on a worker: between the
two, whoever may write the jobs directory could swap a link in (to a file
the daemon may read and the client may not) or a FIFO (whose open would
hold a thread forever). So every open of a job file checks again, on the
descriptor itself: `O_NOFOLLOW` refuses a link as the last part of the path
(the name has no other part: `check_name`), `O_NONBLOCK` lets the open of a
FIFO return, and `fstat` of what was opened must say a regular file. What is
read is then what was checked.

A job's start reads its file several times: the checks (on workers), then
the stream. Another client's upload of the same name may publish a new
version in between, which no check read. So `job.start` takes the file's
`Version` before its checks (`version_of`), and the stream's open must find
that version still there (`open_text(path, version)`), or nothing is sent
(`FileChanged`).
"""

from __future__ import annotations

import errno
import hashlib
import io
import os
import stat
from pathlib import Path
from typing import IO, TextIO

from hostd.protocol.errors import MachineError

_FLAGS = os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC

# A published file as one upload left it: (st_dev, st_ino, st_size, st_mtime_ns). Each
# publish renames a new staging file: another upload's version is another inode, and
# should the file system reuse a freed inode, it is written at another nanosecond.
Version = tuple[int, int, int, int]


class NoSuchFile(MachineError):
    """No regular file of that name in the jobs directory (api.md's 1004)."""

    code = 1004


class FileChanged(NoSuchFile):
    """The version a job's start checked is no longer the file of that name (1004: the
    file asked for is gone, another took its name)."""


def open_binary(path: Path, version: Version | None = None) -> io.BufferedReader:
    """The job file at `path`, opened for reading bytes; NoSuchFile if it is not one,
    FileChanged if it is not `version` (when given)."""
    return open(_open(path, version), "rb")  # the descriptor checked, as a file


def open_text(path: Path, version: Version | None = None) -> TextIO:
    """The job file at `path` as text: UTF-8, an undecodable byte read as U+FFFD, as a
    job's lines are read everywhere; else as `open_binary`."""
    return io.TextIOWrapper(open_binary(path, version), encoding="utf-8", errors="replace")


def version_of(path: Path) -> Version:
    """The version of the job file at `path` now; NoSuchFile if it is not one."""
    with open_binary(path) as f:
        return file_version(f)


def file_version(file: IO[bytes] | IO[str]) -> Version:
    """The version of the job file open in `file`."""
    return _version(os.fstat(file.fileno()))


def sha256(file: IO[bytes]) -> str:
    """The SHA-256, in hex, of what `file` holds from where it stands: a job file's
    bytes, as a job's row keeps them (`Job.file_sha256`) and its analysis is kept by."""
    digest = hashlib.sha256()
    while chunk := file.read(1 << 20):
        digest.update(chunk)
    return digest.hexdigest()


def _version(st: os.stat_result) -> Version:
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


def _open(path: Path, version: Version | None) -> int:
    try:
        fd = os.open(path, _FLAGS)
    except FileNotFoundError:
        raise NoSuchFile(f"no file {path.name!r} in the jobs directory") from None
    except OSError as exc:
        if exc.errno == errno.ELOOP:  # O_NOFOLLOW on a link
            raise NoSuchFile(f"{path.name!r} is not a regular file (a link)") from None
        raise
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise NoSuchFile(f"{path.name!r} is not a regular file")
        if version is not None and _version(st) != version:
            raise FileChanged(
                f"{path.name!r} changed while it was being checked (uploaded again?): "
                "nothing was sent; ask again to check the new version"
            )
        os.set_blocking(fd, True)
    except BaseException:
        os.close(fd)
        raise
    return fd
