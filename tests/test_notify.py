"""The notify protocol against a real datagram socket, as systemd would receive it."""

from __future__ import annotations

import asyncio
import os
import socket
import time
from pathlib import Path

import pytest
from structlog.testing import capture_logs

from hostd.notify import Notifier


def receiver(path: Path) -> socket.socket:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(2)
    return sock


def test_messages_arrive_as_one_datagram_each(tmp_path: Path) -> None:
    with receiver(tmp_path / "notify") as sock:
        notifier = Notifier({"NOTIFY_SOCKET": str(tmp_path / "notify")})
        assert notifier.enabled
        notifier.send(READY=1, STATUS="2 machines: laser1 idle, mill busy")
        notifier.send(STOPPING=1)
        assert sock.recv(4096) == b"READY=1\nSTATUS=2 machines: laser1 idle, mill busy"
        assert sock.recv(4096) == b"STOPPING=1"
        notifier.close()


def test_abstract_socket_names(tmp_path: Path) -> None:
    name = f"hostd-test-{os.getpid()}-{time.monotonic_ns()}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(b"\0" + name.encode())
        sock.settimeout(2)
        notifier = Notifier({"NOTIFY_SOCKET": "@" + name})
        notifier.send(READY=1)
        assert sock.recv(64) == b"READY=1"
        notifier.close()


def test_without_notify_socket_nothing_happens() -> None:
    notifier = Notifier({})
    assert not notifier.enabled
    notifier.send(READY=1)  # no error, no effect


def test_a_receiver_that_does_not_read_never_blocks_the_sender(tmp_path: Path) -> None:
    """Its queue full (10 datagrams by default on Linux), a ping is dropped, not waited for:
    the event loop that sends it is the daemon's."""
    systemd = receiver(tmp_path / "notify")
    notifier = Notifier({"NOTIFY_SOCKET": str(tmp_path / "notify")})
    with capture_logs() as logs:
        for _ in range(1000):
            notifier.send(WATCHDOG=1)
    assert [e["event"] for e in logs] == ["systemd notify failed"]  # once, not a thousand
    assert systemd.recv(100) == b"WATCHDOG=1"
    notifier.send(STATUS="again")
    notifier.close()
    systemd.close()


def test_a_gone_receiver_is_logged_not_raised(tmp_path: Path) -> None:
    notifier = Notifier({"NOTIFY_SOCKET": str(tmp_path / "nobody")})
    notifier.send(READY=1)


@pytest.mark.parametrize(
    ("env", "interval"),
    [
        ({"WATCHDOG_USEC": "2000000"}, 2.0),
        ({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": str(os.getpid())}, 2.0),
        ({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "1"}, None),  # meant for another process
        ({"WATCHDOG_USEC": "0"}, None),
        ({}, None),
    ],
)
def test_watchdog_interval(env: dict[str, str], interval: float | None) -> None:
    assert Notifier(env).watchdog_interval == interval


@pytest.mark.asyncio
async def test_watchdog_pings_at_half_the_interval_while_the_loop_runs(tmp_path: Path) -> None:
    with receiver(tmp_path / "notify") as sock:
        sock.setblocking(False)
        notifier = Notifier({"NOTIFY_SOCKET": str(tmp_path / "notify"), "WATCHDOG_USEC": "100000"})
        task = asyncio.create_task(notifier.watchdog())
        loop = asyncio.get_running_loop()
        pings = [await asyncio.wait_for(loop.sock_recv(sock, 64), 1) for _ in range(3)]
        assert pings == [b"WATCHDOG=1"] * 3

        time.sleep(0.3)  # noqa: ASYNC251 - the event loop stalls on purpose: no ping may go
        stalled = []
        while True:
            try:
                stalled.append(sock.recv(64))
            except BlockingIOError:
                break
        assert stalled == []  # nothing arrived during the stall
        task.cancel()
        notifier.close()


@pytest.mark.asyncio
async def test_an_unhealthy_daemon_stops_pinging(tmp_path: Path) -> None:
    with receiver(tmp_path / "notify") as sock:
        sock.setblocking(False)
        notifier = Notifier({"NOTIFY_SOCKET": str(tmp_path / "notify"), "WATCHDOG_USEC": "40000"})
        healthy = True
        task = asyncio.create_task(notifier.watchdog(lambda: healthy))
        loop = asyncio.get_running_loop()
        assert await asyncio.wait_for(loop.sock_recv(sock, 64), 1) == b"WATCHDOG=1"
        healthy = False
        await asyncio.sleep(0.1)  # several intervals pass with the loop running
        while True:
            try:
                sock.recv(64)  # drain what was sent while still healthy
            except BlockingIOError:
                break
        await asyncio.sleep(0.1)
        with pytest.raises(BlockingIOError):
            sock.recv(64)
        task.cancel()
        notifier.close()


def test_a_receiver_that_stops_reading_never_blocks_the_sender(tmp_path: Path) -> None:
    with receiver(tmp_path / "notify"):
        notifier = Notifier({"NOTIFY_SOCKET": str(tmp_path / "notify")})
        for _ in range(100):  # ten times what the kernel queues for an unread socket
            notifier.send(WATCHDOG=1)
        notifier.close()
