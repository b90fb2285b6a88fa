"""systemd's notify protocol, written against NOTIFY_SOCKET directly.

One datagram per message to the socket systemd names (an abstract socket
when it starts with `@`). With no NOTIFY_SOCKET it does nothing. The
watchdog pings come from a task on the event loop, so a stalled loop stops
them and systemd's watchdog fires: that is the point. Only the main
process may send (NotifyAccess=main), and only if WATCHDOG_PID is unset or
ours. About 15 lines of protocol; no library needed
(../shared/notes/python-stack.md, section 5).
"""

from __future__ import annotations

import asyncio
import os
import socket
from collections.abc import Callable, Mapping

import structlog

log = structlog.get_logger(__name__)


class Notifier:
    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        self._address = _address(env.get("NOTIFY_SOCKET", ""))
        self.watchdog_interval = _watchdog_interval(env)
        self._sock: socket.socket | None = None
        if self._address is not None:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            # Never wait on the receiver: a full queue (systemd busy, a test not reading;
            # Linux queues 10 datagrams by default) must not stop the event loop.
            self._sock.setblocking(False)
        self._failing = False  # the last send failed: the next failure is not logged again

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def send(self, **fields: str | int) -> None:
        """`send(READY=1, STATUS="...")`: one datagram; failures are logged, never raised."""
        if self._sock is None or self._address is None:
            return
        payload = "\n".join(f"{key}={value}" for key, value in fields.items()).encode()
        try:
            self._sock.sendto(payload, self._address)
        except OSError as exc:
            if not self._failing:
                log.warning("systemd notify failed", error=str(exc))
            self._failing = True
        else:
            self._failing = False

    async def watchdog(self, healthy: Callable[[], bool] = lambda: True) -> None:
        """Ping at half the interval systemd asked for, for as long as the loop runs."""
        if self.watchdog_interval is None:
            return
        while True:
            if healthy():
                self.send(WATCHDOG=1)
            await asyncio.sleep(self.watchdog_interval / 2)

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def _address(name: str) -> str | bytes | None:
    if name.startswith("@"):
        return b"\0" + name[1:].encode()
    if name.startswith("/"):
        return name
    return None


def _watchdog_interval(env: Mapping[str, str]) -> float | None:
    usec = env.get("WATCHDOG_USEC", "")
    pid = env.get("WATCHDOG_PID", "")
    if not usec.isdigit() or int(usec) == 0:
        return None
    if pid and pid != str(os.getpid()):
        return None
    return int(usec) / 1_000_000
