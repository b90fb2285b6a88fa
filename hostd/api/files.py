"""The jobs directory: G-code files clients upload, list, delete and start.

A file name is a plain relative name: no separator, no `..`, no NUL, not
hidden (names starting with a dot are the daemon's own: `.staging`), at
most 200 bytes. Anything else is refused before the file system is
touched, so nothing a client sends can reach outside the directory;
symlinks inside it are never followed.

Files arrive through `uploads.py`, which never publishes a partial or mixed
file. Blocking calls: run them with `asyncio.to_thread`.
"""

from __future__ import annotations

import base64
import binascii
import os
import stat
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from hostd.api.uploads import DEFAULT_EXPIRY, Uploaded, Uploads
from hostd.machine.jobfile import Version

MAX_NAME = 200  # file systems stop at 255


class FileNameError(ValueError):
    """A name that is not a plain file name of the jobs directory (-32602)."""


class InvalidData(ValueError):
    """Upload data that cannot be decoded (-32602)."""


class NoSuchFileError(LookupError):
    """No such file in the jobs directory (1004)."""


@dataclass(frozen=True, slots=True)
class FileInfo:
    name: str
    size: int
    modified: str


def check_name(name: str) -> str:
    if not name or name in (".", ".."):
        raise FileNameError("a file name is required")
    if "/" in name or "\\" in name or "\x00" in name:
        raise FileNameError(f"{name!r}: a plain file name, without directories")
    if name.startswith("."):
        raise FileNameError(f"{name!r}: names starting with '.' are reserved")
    try:
        size = len(name.encode("utf-8"))
    except UnicodeEncodeError:  # a lone surrogate: no file system name
        raise FileNameError("the file name is not valid text") from None
    if size > MAX_NAME:
        raise FileNameError(f"file name over {MAX_NAME} bytes")
    if any(ord(c) < 0x20 or ord(c) == 0x7F for c in name):
        raise FileNameError(f"{name!r}: control characters in the name")
    return name


def decode(data: str, encoding: str) -> bytes:
    if encoding == "utf-8":
        return data.encode("utf-8", "surrogatepass")
    try:
        return base64.b64decode(data, validate=True)
    except (binascii.Error, ValueError) as exc:
        raise InvalidData(f"data is not valid base64: {exc}") from None


class JobsDir:
    def __init__(
        self,
        path: Path,
        *,
        quota: int | None = None,
        expiry: float = DEFAULT_EXPIRY,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.path = path
        self.uploads = Uploads(path, quota=quota, expiry=expiry, clock=clock)

    def resolve(self, name: str) -> Path:
        """The path of an existing regular file (not a link) of the directory."""
        path = self.path / check_name(name)
        try:
            st = path.lstat()
        except FileNotFoundError:
            raise NoSuchFileError(f"no file {name!r}") from None
        if not stat.S_ISREG(st.st_mode):
            raise NoSuchFileError(f"{name!r} is not a regular file")
        return path

    def upload(
        self,
        name: str,
        data: bytes,
        *,
        append: bool = False,
        final: bool = True,
        upload_id: str | None = None,
        offset: int | None = None,
        by_name: bool = False,
        after: Version | None = None,
    ) -> Uploaded:
        """Start, continue or finish an upload of `name` (`Uploads.put`)."""
        return self.uploads.put(
            check_name(name),
            data,
            append=append,
            final=final,
            upload_id=upload_id,
            offset=offset,
            by_name=by_name,
            after=after,
        )

    def entries(self) -> list[FileInfo]:
        files = []
        with os.scandir(self.path) as entries:
            for entry in entries:
                if entry.name.startswith(".") or not entry.is_file(follow_symlinks=False):
                    continue
                st = entry.stat(follow_symlinks=False)
                modified = datetime.fromtimestamp(st.st_mtime, UTC)
                files.append(
                    FileInfo(
                        entry.name,
                        st.st_size,
                        modified.isoformat(timespec="seconds").replace("+00:00", "Z"),
                    )
                )
        return sorted(files, key=lambda f: f.name)

    def delete(self, name: str) -> None:
        self.resolve(name).unlink()

    def clean(self) -> list[str]:
        """Start-up: remove every upload's staging (none survives a restart), and the
        temp and staging files older versions left beside the job files."""
        removed = self.uploads.clean()
        with os.scandir(self.path) as entries:
            for entry in entries:
                name = entry.name
                legacy = name.startswith(".tmp-") or (name[:1] == "." and name.endswith(".upload"))
                if legacy and entry.is_file(follow_symlinks=False):
                    os.unlink(entry.path)
                    removed.append(name)
        return removed
