"""The jobs directory: G-code files clients upload, list, delete and start.

A file name is a plain relative name: no separator, no `..`, no NUL, not
hidden (a leading dot is the daemon's own staging), at most 200 bytes.
Anything else is refused before the file system is touched, so nothing a
client sends can reach outside the directory (symlinks inside it are not
followed either: `O_NOFOLLOW`-style checks via `lstat`).

Writes are atomic: a temp file in the same directory, fsync, rename. A
large file may come in chunks (`append`); chunks sent with `final=False`
collect in a hidden staging file, published by the chunk with
`final=True`, so a half-uploaded program never appears as a job file.
Blocking calls: run them with `asyncio.to_thread`.
"""

from __future__ import annotations

import base64
import binascii
import os
import shutil
import stat
import tempfile
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

MAX_NAME = 200  # the staging name adds 8 bytes; file systems stop at 255


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
    def __init__(self, path: Path) -> None:
        self.path = path

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

    def upload(self, name: str, data: bytes, *, append: bool = False, final: bool = True) -> int:
        """Write or extend a file; returns the size of what is (or will be) published."""
        target = self.path / check_name(name)
        staging = self.path / f".{name}.upload"
        if append and staging.exists():
            with staging.open("ab") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
        else:
            base = self._existing(target) if append else None
            tmp = self._temp()
            with open(tmp, "r+b") as f:
                if base is not None:
                    with base.open("rb") as src:
                        shutil.copyfileobj(src, f)
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, staging)
        size = staging.stat().st_size
        if final:
            os.replace(staging, target)
        return size

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
        """Remove staging and temp files a stopped daemon left (an upload never finished)."""
        removed = []
        with os.scandir(self.path) as entries:
            for entry in entries:
                name = entry.name
                staged = name.startswith(".") and name.endswith(".upload")
                if (staged or name.startswith(".tmp-")) and entry.is_file(follow_symlinks=False):
                    os.unlink(entry.path)
                    removed.append(name)
        return removed

    def _existing(self, target: Path) -> Path | None:
        try:
            st = target.lstat()
        except FileNotFoundError:
            return None
        return target if stat.S_ISREG(st.st_mode) else None

    def _temp(self) -> str:
        fd, tmp = tempfile.mkstemp(dir=self.path, prefix=".tmp-")
        os.close(fd)
        return tmp
