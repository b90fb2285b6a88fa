"""Who is on the other end of the socket, and whether they may talk to the daemon.

The socket file's mode (0600, or 0660 with a group) is the first gate; this
is the second: the kernel tells us the peer's pid, uid and gid at connect
time (SO_PEERCRED), which a client cannot forge, and the policy decides on
those alone.
"""

from __future__ import annotations

import grp
import os
import pwd
import socket
import struct
from collections.abc import Set
from dataclasses import dataclass
from typing import Any, Self

_UCRED = struct.Struct("3i")


@dataclass(frozen=True, slots=True)
class PeerCred:
    """The connecting process as the kernel saw it when it called connect()."""

    pid: int
    uid: int
    gid: int


def peer_credentials(sock: Any) -> PeerCred:
    """SO_PEERCRED of a connected Unix socket (a `socket.socket` or asyncio's TransportSocket).

    Raises OSError if the kernel will not say.
    """
    raw = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, _UCRED.size)
    pid, uid, gid = _UCRED.unpack(raw)
    return PeerCred(pid, uid, gid)


def group_id(name: str) -> int:
    """The gid of a group name, with an error that says what was looked up."""
    try:
        return grp.getgrnam(name).gr_gid
    except KeyError:
        raise ValueError(f"unknown group {name!r}") from None


def _groups_of(uid: int) -> set[int]:
    """The uid's login group and supplementary groups from NSS; empty for an unknown uid."""
    try:
        user = pwd.getpwuid(uid)
    except KeyError:
        return set()
    return set(os.getgrouplist(user.pw_name, user.pw_gid))


@dataclass(frozen=True, slots=True)
class AccessPolicy:
    """Peers allowed in: by uid, or by membership of one of the allowed groups.

    Membership is the peer's effective gid, or the groups the user database
    gives the peer's user (its login group and the groups listing it). The
    user database is consulted only when the uid and the gid alone do not
    decide, since NSS can be slow (LDAP): call `allows` off the event loop.
    """

    allowed_uids: Set[int]
    allowed_gids: Set[int]

    def __post_init__(self) -> None:
        object.__setattr__(self, "allowed_uids", frozenset(self.allowed_uids))
        object.__setattr__(self, "allowed_gids", frozenset(self.allowed_gids))

    @classmethod
    def default(cls, group: str | None = None) -> Self:
        """Root, the daemon's own user, and the members of `group` when given.

        Raises ValueError for an unknown group: a typo must stop start-up, not
        silently lock everyone out.
        """
        uids = {0, os.getuid()}
        gids = {group_id(group)} if group is not None else set()
        return cls(uids, gids)

    def allows(self, peer: PeerCred) -> bool:
        if peer.uid in self.allowed_uids or peer.gid in self.allowed_gids:
            return True
        if not self.allowed_gids:
            return False
        return not self.allowed_gids.isdisjoint(_groups_of(peer.uid))
