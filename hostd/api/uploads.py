"""Uploads into the jobs directory, so that a corrupted program is never published.

A job file is a program a machine will run: a half-written file, or one
mixing two uploads, published while the client is told it succeeded, can
break a tool or start a fire. So (docs/api.md has the contract):

- Every upload, whole or in chunks, writes its own staging file
  `.staging/<id>` under a random id, created with `O_CREAT|O_EXCL|O_NOFOLLOW`
  and, for each later chunk, reopened with `O_NOFOLLOW` and checked to be
  the very file it created at the size it left it. Two clients, a retry and
  a restart never share or mix bytes, and a planted link is never followed.
- A chunk says where it starts (`offset`). A retry of bytes already staged
  changes nothing; anything else that does not continue the upload is
  refused with the offset that would.
- A chunk that fails (a full disk) is cut off again: staging is as it was
  before it, and the same chunk may be sent again.
- Only the final chunk publishes: fsync, one rename onto the name, fsync of
  the directory. A flush that fails discards the upload (what reached the
  disk is unknown).
- Ids live in memory only: after a restart they are unknown and the
  start-up `clean` removes their staging, so a restart publishes nothing.
- api.md's own chunking, `append: true` with neither `upload` nor `offset`,
  continues the version of the file its connection last published
  (`after`, kept per connection by appends.py): a copy of it with the chunk
  is published whole, in one rename, and only while that version is still
  the one published. Another client's file, one deleted, or one from before
  a restart is never appended to: the chunk is refused.
- An upload without a chunk for `expiry` seconds is removed, and an
  optional quota bounds published files plus staging.

Names reach this module already checked (`files.check_name`). Blocking
calls: run them with `asyncio.to_thread`. One lock serialises the uploads
of a directory; the disk, not the lock, is what they wait for.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import secrets
import stat
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from hostd.machine.jobfile import Version

STAGING = ".staging"
DEFAULT_EXPIRY = 3600.0  # seconds without a chunk before an upload is abandoned
_FULL = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})
_DIR = os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC
_NOFOLLOW = os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK  # a planted FIFO must not block us


class NoSuchUpload(LookupError):
    """An upload id that is not open here: expired, finished, or from before a restart (1004)."""


class ChunkError(ValueError):
    """A chunk that does not fit its upload (-32602); `expected` is the offset that would."""

    def __init__(self, message: str, expected: int) -> None:
        super().__init__(message)
        self.expected = expected


class StorageError(Exception):
    """The data could not be stored (1009). `reason`: "full" (no space, or the
    file system's own quota), "quota" (the jobs quota) or "io" (anything else
    the file system refused). The message says what became of the upload."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason
        self.message = message


@dataclass(frozen=True, slots=True)
class Uploaded:
    """The answer to one call: `upload` is the id while the upload stays open;
    `version` is the file this call published, if it published one."""

    name: str
    size: int
    upload: str | None = None
    version: Version | None = None


@dataclass(slots=True)
class _Open:
    name: str
    size: int  # what is staged; the staging file must have exactly this size
    inode: tuple[int, int]  # (st_dev, st_ino) of the file this upload created, and no other
    touched: float


@dataclass(frozen=True, slots=True)
class _Done:
    """A published upload, kept until it expires so a retried final chunk is answered again."""

    name: str
    size: int
    final: tuple[int, int, bytes]  # offset, length and SHA-256 of the final chunk
    at: float
    version: Version


class Uploads:
    """The staging area of one jobs directory and the uploads open in it."""

    def __init__(
        self,
        path: Path,
        *,
        quota: int | None = None,
        expiry: float = DEFAULT_EXPIRY,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.path = path
        self.quota = quota  # bytes of published files plus staging; None: no limit
        self.expiry = expiry
        self._clock = clock
        self._lock = threading.Lock()
        self._open: dict[str, _Open] = {}
        self._done: dict[str, _Done] = {}

    def put(
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
        """One `file.upload` call: start an upload, continue it at `offset`, or finish it.

        Without `upload_id` a new upload starts: empty, or with `append` a
        copy of the published file, whose size `offset` must be (so a chunk
        can never be appended to a file its client did not mean). `by_name`:
        api.md's append without an offset, which continues `after`, the
        version its connection last published (None: it published none), and
        only while that version is the one published.
        """
        with self._lock:
            try:
                with self._dirs() as (jobs, staging):
                    self._expire(staging)
                    if upload_id is not None and upload_id in self._done:
                        return self._replay(upload_id, name, data, offset, final)
                    if upload_id is not None:
                        return self._chunk(jobs, staging, upload_id, name, data, offset, final)
                    new, start = self._begin(jobs, staging, name, append, offset, by_name, after)
                    try:
                        return self._chunk(jobs, staging, new, name, data, start, final)
                    except BaseException:  # the client never learns this id: nothing may stay
                        self._discard(staging, new)
                        raise
            except OSError as exc:
                raise _storage(exc, "cannot use the jobs directory", "nothing was stored") from None

    def expire(self) -> list[str]:
        """Remove uploads without a chunk for `expiry` seconds; the ids whose staging went."""
        with self._lock, self._dirs() as (_, staging):
            return self._expire(staging)

    def abort(self, upload_id: str) -> bool:
        """Forget an open upload and remove its staging now (its sender failed or left);
        whether it was open."""
        with self._lock, self._dirs() as (_, staging):
            known = upload_id in self._open
            self._discard(staging, upload_id)
            return known

    def clean(self) -> list[str]:
        """Start-up: forget every upload and remove all staging; the ids removed."""
        with self._lock, self._dirs() as (_, staging):
            self._open.clear()
            self._done.clear()
            return self._expire(staging)

    # -- one upload ------------------------------------------------------------

    def _begin(
        self,
        jobs: int,
        staging: int,
        name: str,
        append: bool,
        offset: int | None,
        by_name: bool = False,
        after: Version | None = None,
    ) -> tuple[str, int]:
        """A new staging file, empty or a copy of the published file; its id and size."""
        source, size = self._published(jobs, name) if append else (None, 0)
        try:
            if by_name:
                _check_continues(name, source, size, after)
                offset = size
            if append and offset != size:
                raise ChunkError(
                    f"appending to {name!r} needs offset {size}, the size of the file now"
                    " (or continue an upload with its `upload` id)",
                    size,
                )
            if not append and offset not in (None, 0):
                raise ChunkError(
                    "a new upload starts at offset 0 (pass `upload` to continue one)", 0
                )
            self._check_quota(jobs, staging, size)
            upload_id = secrets.token_hex(16)
            flags = os.O_RDWR | os.O_CREAT | os.O_EXCL | _NOFOLLOW
            fd = os.open(upload_id, flags, 0o600, dir_fd=staging)
            st = os.fstat(fd)
            self._open[upload_id] = _Open(name, 0, (st.st_dev, st.st_ino), self._clock())
            try:
                while source is not None and self._open[upload_id].size < size:
                    block = os.read(source, min(1 << 20, size - self._open[upload_id].size))
                    if not block:  # cut in place: appending goes on from its size now
                        now = os.fstat(source).st_size
                        raise ChunkError(
                            f"{name!r} changed while it was copied: it has {now} bytes now",
                            now,
                        )
                    self._append(fd, staging, upload_id, block)
            except BaseException:
                self._discard(staging, upload_id)
                raise
            finally:
                os.close(fd)
            return upload_id, size
        finally:
            if source is not None:
                os.close(source)

    def _chunk(
        self,
        jobs: int,
        staging: int,
        upload_id: str,
        name: str,
        data: bytes,
        offset: int | None,
        final: bool,
    ) -> Uploaded:
        up = self._open.get(upload_id)
        if up is None:
            raise NoSuchUpload(
                f"no upload {upload_id}: it expired ({self.expiry:g} s without a chunk),"
                " was finished, or the daemon restarted since; start the upload again"
            )
        up.touched = self._clock()
        if up.name != name:
            raise ChunkError(f"upload {upload_id} is for {up.name!r}, not {name!r}", up.size)
        if offset is None:
            raise ChunkError(f"a chunk of upload {upload_id} needs `offset` ({up.size})", up.size)
        fd = self._reopen(staging, upload_id, up)
        written = 0  # the staging file's mtime once flushed, for the version published
        try:
            end = offset + len(data)
            if offset == up.size:
                self._check_quota(jobs, staging, len(data))
                self._append(fd, staging, upload_id, data)
            elif end > up.size or os.pread(fd, len(data), offset) != data:
                raise ChunkError(
                    f"upload {upload_id} has {up.size} bytes: a chunk at offset {offset}"
                    f" of {len(data)} bytes neither continues it nor repeats what is staged;"
                    f" expected offset {up.size}",
                    up.size,
                )
            if final and end != up.size:
                raise ChunkError(
                    f"the final chunk must end the upload: {up.size} bytes are staged,"
                    f" this chunk ends at {end}; expected offset {up.size}",
                    up.size,
                )
            if final:
                try:
                    os.fsync(fd)
                except OSError as exc:  # what reached the disk is unknown: never publish it
                    self._discard(staging, upload_id)
                    raise _storage(exc, "cannot flush the upload", "it is discarded") from None
                written = os.fstat(fd).st_mtime_ns  # a rename keeps it
        finally:
            os.close(fd)
        if not final:
            return Uploaded(name, up.size, upload_id)
        try:
            os.replace(upload_id, name, src_dir_fd=staging, dst_dir_fd=jobs)
        except OSError as exc:
            raise _storage(exc, f"cannot publish {name!r}", "the file was not published") from None
        del self._open[upload_id]
        digest = hashlib.sha256(data).digest()
        version = (*up.inode, up.size, written)
        chunk = (offset, len(data), digest)
        self._done[upload_id] = _Done(name, up.size, chunk, self._clock(), version)
        try:
            os.fsync(jobs)
        except OSError as exc:
            raise _storage(
                exc, f"{name!r} is published whole", "its name may not survive a power cut"
            ) from None
        return Uploaded(name, up.size, version=version)

    def _replay(
        self, upload_id: str, name: str, data: bytes, offset: int | None, final: bool
    ) -> Uploaded:
        """A retried final chunk (its answer was lost) gets the same answer, and nothing else."""
        done = self._done[upload_id]
        chunk = (offset, len(data), hashlib.sha256(data).digest())
        if final and name == done.name and chunk == done.final:
            return Uploaded(done.name, done.size, version=done.version)
        raise NoSuchUpload(
            f"upload {upload_id} is finished: {done.name!r} was published with {done.size} bytes"
        )

    def _append(self, fd: int, staging: int, upload_id: str, data: bytes) -> None:
        """Write at the end of staging; on failure cut staging back to its size before."""
        up = self._open[upload_id]
        before = up.size
        try:
            os.lseek(fd, before, os.SEEK_SET)
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view) :]
        except OSError as exc:
            try:
                os.ftruncate(fd, before)
            except OSError:
                self._discard(staging, upload_id)
                lost = "staging could not be cut back, so the upload is discarded: start it again"
                raise _storage(exc, "cannot store the chunk", lost) from None
            kept = f"nothing of it was kept, the upload has {before} bytes"
            raise _storage(exc, "cannot store the chunk", kept) from None
        up.size = before + len(data)

    def _reopen(self, staging: int, upload_id: str, up: _Open) -> int:
        """The upload's own staging file, never a link nor another file; else it is discarded."""
        try:
            fd = os.open(upload_id, os.O_RDWR | _NOFOLLOW, dir_fd=staging)
        except OSError as exc:
            self._discard(staging, upload_id)
            raise StorageError(
                "io",
                f"the staging of upload {upload_id} is gone or is a link ({exc.strerror});"
                " the upload is discarded, start it again",
            ) from None
        st = os.fstat(fd)
        if (st.st_dev, st.st_ino) != up.inode or st.st_size != up.size:
            os.close(fd)
            self._discard(staging, upload_id)
            raise StorageError(
                "io",
                f"the staging of upload {upload_id} was changed by something else;"
                " the upload is discarded, start it again",
            )
        return fd

    # -- the directory --------------------------------------------------------

    @contextlib.contextmanager
    def _dirs(self) -> Iterator[tuple[int, int]]:
        """The jobs directory and its staging directory, opened for `dir_fd` use."""
        jobs = os.open(self.path, _DIR)
        try:
            staging = self._staging(jobs)
            try:
                yield jobs, staging
            finally:
                os.close(staging)
        finally:
            os.close(jobs)

    def _staging(self, jobs: int) -> int:
        """`.staging`, made if missing; a link or file in its place is removed, never followed."""
        try:
            return os.open(STAGING, _DIR | os.O_NOFOLLOW, dir_fd=jobs)
        except FileNotFoundError:
            pass
        except OSError as exc:
            if exc.errno not in (errno.ELOOP, errno.ENOTDIR):
                raise
            os.unlink(STAGING, dir_fd=jobs)
        os.mkdir(STAGING, 0o700, dir_fd=jobs)
        return os.open(STAGING, _DIR | os.O_NOFOLLOW, dir_fd=jobs)

    def _published(self, jobs: int, name: str) -> tuple[int | None, int]:
        """The published regular file `name`, open, and its size; (None, 0) if there is none."""
        try:
            fd = os.open(name, os.O_RDONLY | _NOFOLLOW, dir_fd=jobs)
        except FileNotFoundError:
            return None, 0
        except OSError as exc:
            if exc.errno == errno.ELOOP:  # a link is no job file: publishing replaces it
                return None, 0
            raise
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            os.close(fd)
            return None, 0
        return fd, st.st_size

    def _check_quota(self, jobs: int, staging: int, more: int) -> None:
        if self.quota is None or more <= 0:
            return
        used = _usage(jobs) + _usage(staging)
        if used + more > self.quota:
            raise StorageError(
                "quota",
                f"the jobs quota of {self.quota} bytes would be exceeded: {used} are used and"
                f" this needs {more} more; nothing of it was stored (delete files, or wait for"
                " abandoned uploads to expire)",
            )

    def _expire(self, staging: int) -> list[str]:
        now = self._clock()
        removed = [i for i, up in self._open.items() if now - up.touched >= self.expiry]
        for upload_id in removed:
            self._discard(staging, upload_id)
        self._done = {i: d for i, d in self._done.items() if now - d.at < self.expiry}
        for entry in os.listdir(staging):  # left by a daemon before this one: nobody owns it
            if entry not in self._open:
                with contextlib.suppress(FileNotFoundError, IsADirectoryError):
                    os.unlink(entry, dir_fd=staging)
                removed.append(entry)
        return removed

    def _discard(self, staging: int, upload_id: str) -> None:
        self._open.pop(upload_id, None)
        with contextlib.suppress(FileNotFoundError):
            os.unlink(upload_id, dir_fd=staging)


def _check_continues(name: str, source: int | None, size: int, after: Version | None) -> None:
    """An append by name continues `after`, the file as its connection last published it,
    or nothing: never another client's file, one deleted, nor one from before a restart."""
    how = (
        "nothing was appended; upload the whole file again (or give `offset`"
        f" {size} to append to {name!r} as it is now)"
    )
    if after is None:
        raise ChunkError(
            f"`append` without `offset` continues the file this connection last uploaded"
            f" as {name!r}, and it uploaded none (a new connection, the daemon restarted"
            f" since, or a request without a connection, as over MQTT): {how}",
            size,
        )
    if source is None:
        raise ChunkError(f"{name!r} was deleted since this connection uploaded it: {how}", 0)
    st = os.fstat(source)
    if (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns) != after:
        raise ChunkError(
            f"{name!r} was replaced by another upload since this connection uploaded it: {how}",
            size,
        )


def _usage(dir_fd: int) -> int:
    """Bytes of the regular files directly in the directory (links and directories: none)."""
    total = 0
    for name in os.listdir(dir_fd):
        with contextlib.suppress(FileNotFoundError):
            st = os.lstat(name, dir_fd=dir_fd)
            if stat.S_ISREG(st.st_mode):
                total += st.st_size
    return total


def _storage(exc: OSError, what: str, outcome: str) -> StorageError:
    reason = "full" if exc.errno in _FULL else "io"
    cause = os.strerror(exc.errno).lower() if exc.errno else str(exc)
    return StorageError(reason, f"{what}: {cause}; {outcome}")
