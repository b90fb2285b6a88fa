"""The socket file: where it may live, how it is born, when an old one may be replaced.

Clients trust whatever answers at the socket path, so the path must be one
only the daemon (or root) can change:

- Its directory must not let anyone else replace entries: owned by root or
  the daemon's user, and not writable by its group or others unless sticky
  (as /tmp is: there only a file's owner may remove or rename it). Otherwise
  another user could swap the socket for their own, after the daemon
  started, and answer its clients.
- Whatever is at the path already is left alone unless it is a socket
  nobody listens on (what a killed daemon leaves): not a symlink someone
  planted, not a regular file, not a live daemon's socket.
- The socket is born with the umask already at 0177, so it exists at 0600
  from its first instant, then gets its group, then its final mode (0660
  with a group, else 0600). It is never wider than its final mode, and never
  open to a group it does not end with.

Every refusal is a `SocketPathError` whose message is one line for the
operator, naming the path and what to do.
"""

from __future__ import annotations

import contextlib
import os
import socket
import stat
from dataclasses import dataclass
from typing import Final

import structlog

log = structlog.get_logger(__name__)

BIRTH_UMASK: Final = 0o177  # a new socket is 0600: the owner only
GROUP_MODE: Final = 0o660
OWNER_MODE: Final = 0o600


class SocketPathError(Exception):
    """The socket path cannot be used; the message says why in one line."""


@dataclass(frozen=True, slots=True)
class BoundSocket:
    """A socket bound at `path`, not yet listening, and the file's identity."""

    sock: socket.socket
    path: str
    inode: tuple[int, int]  # (st_dev, st_ino): to tell our file from a replacement


def final_mode(gid: int | None) -> int:
    """0660 when a group is to use the socket, else 0600."""
    return GROUP_MODE if gid is not None else OWNER_MODE


def check_path(path: str) -> None:
    """Raise SocketPathError unless a daemon could listen at `path` now.

    Changes nothing: `hostd serve` calls it before building anything, so a
    bad path is one line at once rather than an error after the machines
    have been set up. `prepare` checks again when it is time to bind.
    """
    _check_directory(os.path.dirname(os.path.abspath(path)))
    _existing(path)


def prepare(path: str) -> None:
    """Make room for the socket: as `check_path`, then remove a stale socket."""
    _check_directory(os.path.dirname(os.path.abspath(path)))
    if _existing(path):
        try:
            os.unlink(path)
        except FileNotFoundError:
            return
        except OSError as e:
            raise SocketPathError(f"cannot remove the stale socket {path}: {e.strerror}") from e
        log.info("removed stale socket", path=path)


def bind(path: str, gid: int | None) -> BoundSocket:
    """Bind a Unix stream socket at `path`: born 0600, then group `gid`, then its final mode.

    The umask is process-wide. It is changed for the bind() call alone, on
    the event loop thread at start-up; a file another thread (an
    `asyncio.to_thread` worker, say SQLite's journal) creates in that instant
    is born stricter than it asked for, never wider.
    """
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    bound = False
    try:
        old = os.umask(BIRTH_UMASK)
        try:
            sock.bind(path)
            bound = True
        except OSError as e:
            raise SocketPathError(f"cannot create the socket {path}: {e.strerror or e}") from e
        finally:
            os.umask(old)
        if gid is not None:
            try:
                os.chown(path, -1, gid, follow_symlinks=False)
            except OSError as e:
                raise SocketPathError(f"cannot give {path} group {gid}: {e.strerror}") from e
        st = os.lstat(path)
        if not stat.S_ISSOCK(st.st_mode):  # chmod follows symlinks: do not let a swap redirect it
            raise SocketPathError(f"{path} was replaced while binding")
        os.chmod(path, final_mode(gid))
    except BaseException:
        sock.close()
        if bound:
            with contextlib.suppress(OSError):
                os.unlink(path)
        raise
    return BoundSocket(sock, path, (st.st_dev, st.st_ino))


def unlink_own(path: str, inode: tuple[int, int]) -> None:
    """Remove the socket file, unless someone replaced it with another since we bound it."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    if (st.st_dev, st.st_ino) != inode:
        log.warning("socket path no longer ours; left in place", path=path)
        return
    os.unlink(path)


def _check_directory(directory: str) -> None:
    """Refuse a directory in which someone but root and us could replace the socket."""
    try:
        st = os.stat(directory)
    except FileNotFoundError:
        raise SocketPathError(
            f"the socket's directory {directory} does not exist; create it first"
        ) from None
    except OSError as e:
        raise SocketPathError(f"cannot use the socket's directory {directory}: {e.strerror}") from e
    if not stat.S_ISDIR(st.st_mode):
        raise SocketPathError(f"the socket's directory {directory} is not a directory")
    mode = stat.S_IMODE(st.st_mode)
    if st.st_uid not in (0, os.geteuid()):
        raise SocketPathError(
            f"the socket's directory {directory} belongs to uid {st.st_uid}, who could replace"
            " the socket; use a directory owned by root or the daemon's user"
        )
    if mode & (stat.S_IWGRP | stat.S_IWOTH) and not mode & stat.S_ISVTX:
        who = "others" if mode & stat.S_IWOTH else "its group"
        raise SocketPathError(
            f"the socket's directory {directory} is writable by {who} (mode {mode:04o}) without"
            f" the sticky bit, so they could replace the socket; use a directory only the"
            f" daemon's user can write (chmod go-w {directory})"
        )


def _existing(path: str) -> bool:
    """What is at `path` already: nothing (False), a stale socket (True), or a refusal."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return False
    except OSError as e:
        raise SocketPathError(f"cannot use the socket path {path}: {e.strerror}") from e
    if stat.S_ISLNK(st.st_mode):
        raise SocketPathError(
            f"{path} is a symbolic link; refusing to follow or remove it (remove it yourself"
            " if it is yours)"
        )
    if not stat.S_ISSOCK(st.st_mode):
        raise SocketPathError(f"{path} exists and is not a socket; refusing to remove it")
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    probe.setblocking(False)
    try:
        probe.connect(path)
    except ConnectionRefusedError:
        return True  # stale: left behind by a daemon that died
    except FileNotFoundError:
        return False
    except BlockingIOError:  # listening, its backlog full: very much alive
        raise SocketPathError(f"{path} is in use: another process listens on it") from None
    except OSError as e:
        raise SocketPathError(f"cannot tell whether {path} is in use: {e.strerror}") from None
    finally:
        probe.close()
    raise SocketPathError(f"{path} is in use: another process listens on it")
