"""Peer credentials and the access policy."""

from __future__ import annotations

import grp
import os
import socket
from types import SimpleNamespace

import pytest

from hostd.api.peer import AccessPolicy, PeerCred, group_id, peer_credentials

STRANGER = PeerCred(pid=1234, uid=54321, gid=54321)


def test_the_kernel_names_the_peer_process() -> None:
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    with a, b:
        assert peer_credentials(a) == PeerCred(os.getpid(), os.getuid(), os.getgid())


def test_the_default_policy_lets_in_root_and_the_daemons_user_only() -> None:
    policy = AccessPolicy.default()
    assert policy.allows(PeerCred(1, 0, 0))
    assert policy.allows(PeerCred(1, os.getuid(), 54321))
    assert policy.allows(STRANGER) is (os.getuid() == STRANGER.uid)


def test_the_default_policy_lets_in_the_configured_group() -> None:
    name = grp.getgrgid(os.getgid()).gr_name
    policy = AccessPolicy.default(group=name)
    assert os.getgid() in policy.allowed_gids
    assert policy.allows(PeerCred(1, 54321, os.getgid()))


def test_an_unknown_group_stops_start_up() -> None:
    with pytest.raises(ValueError, match="unknown group 'no-such-group-here'"):
        AccessPolicy.default(group="no-such-group-here")
    with pytest.raises(ValueError, match="unknown group"):
        group_id("no-such-group-here")


def test_a_supplementary_group_from_the_user_database_counts(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    user = SimpleNamespace(pw_name="operator", pw_gid=54321)
    monkeypatch.setattr("hostd.api.peer.pwd.getpwuid", lambda uid: user)
    monkeypatch.setattr("hostd.api.peer.os.getgrouplist", lambda name, gid: [gid, 777])
    assert AccessPolicy(set(), {777}).allows(STRANGER)
    assert not AccessPolicy(set(), {778}).allows(STRANGER)


def test_an_unknown_uid_is_only_let_in_by_uid_or_gid(monkeypatch: pytest.MonkeyPatch) -> None:
    def unknown(uid: int) -> None:
        raise KeyError(uid)

    monkeypatch.setattr("hostd.api.peer.pwd.getpwuid", unknown)
    assert not AccessPolicy(set(), {777}).allows(STRANGER)
    assert AccessPolicy(set(), {STRANGER.gid}).allows(STRANGER)
    assert AccessPolicy({STRANGER.uid}, set()).allows(STRANGER)
