"""A job file opened as what the API checked it to be: a regular file of the jobs
directory, never a link, a FIFO or a device.

The API checks a name before anything opens it (`JobsDir.resolve`: `lstat`,
a regular file). The file is opened later, often on a worker: between the
two, whoever may write the jobs directory could swap a link in (to a file
the daemon may read and the client may not) or a FIFO (whose open would
hold a thread forever). So every open of a job file checks again, on the
descriptor itself: `O_NOFOLLOW` refuses a link as the last part of the path
(the name has no other part: `check_name`), `O_NONBLOCK` lets the open of a
FIFO return, and `fstat` of what was opened must say a regular file. What is
read is then what was checked.
"""

from __future__ import annotations

import errno
import io
import os
import stat
from pathlib import Path
from typing import TextIO

from hostd.protocol.errors import MachineError

_FLAGS = os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC


class NoSuchFile(MachineError):
    """No regular file of that name in the jobs directory (api.md's 1004)."""

    code = 1004


def open_binary(path: Path) -> io.BufferedReader:
    """The job file at `path`, opened for reading bytes; NoSuchFile if it is not one."""
    return open(_open(path), "rb")  # the descriptor checked, as a file


def open_text(path: Path) -> TextIO:
    """The job file at `path` as text: UTF-8, an undecodable byte read as U+FFFD, as a
    job's lines are read everywhere; NoSuchFile if it is not one."""
    return io.TextIOWrapper(open_binary(path), encoding="utf-8", errors="replace")


def _open(path: Path) -> int:
    try:
        fd = os.open(path, _FLAGS)
    except FileNotFoundError:
        raise NoSuchFile(f"no file {path.name!r} in the jobs directory") from None
    except OSError as exc:
        if exc.errno == errno.ELOOP:  # O_NOFOLLOW on a link
            raise NoSuchFile(f"{path.name!r} is not a regular file (a link)") from None
        raise
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise NoSuchFile(f"{path.name!r} is not a regular file")
        os.set_blocking(fd, True)
    except BaseException:
        os.close(fd)
        raise
    return fd
