"""A machine's link: its data channel and optional control channel, as one object.

Events flow up: every line either channel reads, and the loss of the link,
arrive in one inbox in the order they happened, read in batches by the one
task that owns the link. Bytes flow down: lines on the data channel, realtime
bytes and queries on the control channel (the data channel when there is only
one). Losing either channel loses the link: the machine is gone.

The inbox is bounded: past `INBOX_HIGH` unread events the link stops reading
the device (the controller's own output then blocks, as on a real USB
endpoint), and reads again as soon as the owner has taken the events.
"""

from __future__ import annotations

import asyncio
import os
import time
from collections import deque
from dataclasses import dataclass
from enum import StrEnum
from functools import partial
from operator import itemgetter
from typing import Protocol

from hostd.link.serial import SerialChannel

# A write's lines each end in LF: their last bytes, read in C (`bytes.endswith` parses its
# arguments at every call: half the cost of a job's write).
_LAST_BYTE = itemgetter(-1)
_LF_ONLY = frozenset(b"\n")

INBOX_HIGH = 4096


class Channel(StrEnum):
    DATA = "data"
    CONTROL = "control"


@dataclass(frozen=True, slots=True)
class LineReceived:
    channel: Channel
    line: bytes
    at: float  # time.monotonic()


@dataclass(frozen=True, slots=True)
class LinkLost:
    channel: Channel
    reason: str


LinkEvent = LineReceived | LinkLost


class Receiver(Protocol):
    """Who takes a link's lines as they are read, in the read's own callback."""

    def link_lines(self, channel: Channel, lines: list[bytes]) -> None: ...
    def link_lost(self, reason: str) -> None: ...


class Link:
    """`await Link.open(...)`, then `await link.read()` in one task; `await link.close()`."""

    def __init__(self, receiver: Receiver | None = None) -> None:
        self._receiver = receiver
        self._inbox: deque[LinkEvent] = deque()
        self._wakeup = asyncio.Event()
        self._channels: dict[Channel, SerialChannel] = {}
        self._paused = False
        self.lost: LinkLost | None = None

    @classmethod
    async def open(
        cls,
        data_path: str,
        control_path: str | None = None,
        baudrate: int = 115200,
        receiver: Receiver | None = None,
    ) -> Link:
        """Open the control port first, then the data port (g2core assigns roles by open order).

        With a `receiver`, lines go to it as they are read (no inbox, no task
        switch a line) and the loss too; `read()` is then not used.
        Raises LinkError with the device and the reason; nothing stays open on failure.
        """
        link = cls(receiver)
        order = [(Channel.DATA, data_path)]
        if control_path is not None:
            order.insert(0, (Channel.CONTROL, control_path))
        try:
            for name, path in order:
                link._channels[name] = await SerialChannel.open(
                    path,
                    baudrate,
                    # With a receiver, a read's lines go straight to it.
                    on_lines=partial(receiver.link_lines if receiver else link._on_lines, name),
                    on_lost=partial(link._on_lost, name),
                )
        except BaseException:
            await link.close()
            raise
        return link

    @property
    def dual(self) -> bool:
        return Channel.CONTROL in self._channels

    def path(self, channel: Channel) -> str:
        return self._channel(channel).path

    # reading

    async def read(self) -> list[LinkEvent]:
        """Every event since the last read, waiting for at least one.

        After the link is lost this keeps returning the `LinkLost` event.
        """
        while not self._inbox:
            if self.lost is not None:
                return [self.lost]
            self._wakeup.clear()
            await self._wakeup.wait()
        events = list(self._inbox)
        self._inbox.clear()
        if self._paused:
            self._set_reading(True)
        return events

    def _on_lines(self, channel: Channel, lines: list[bytes]) -> None:
        at = time.monotonic()
        self._inbox.extend(LineReceived(channel, line, at) for line in lines)
        self._wakeup.set()
        if len(self._inbox) >= INBOX_HIGH and not self._paused:
            self._set_reading(False)

    def _on_lost(self, channel: Channel, reason: str) -> None:
        if self.lost is None:
            self.lost = LinkLost(channel, reason)
            if self._receiver is not None:
                self._receiver.link_lost(reason)
                return
            self._inbox.append(self.lost)
            self._wakeup.set()

    def _set_reading(self, on: bool) -> None:
        self._paused = not on
        for ch in self._channels.values():
            ch.set_reading(on)

    # writing

    def write_line(self, data: bytes) -> bool:
        """A whole encoded line (ending in LF) on the data channel."""
        return self._write(Channel.DATA, data)

    def write_lines(self, lines: list[bytes], *, control: bool = False) -> bool:
        """Whole encoded lines in one write: on the data channel, or with `control` on
        the control channel (the only one, on a one-port link)."""
        data = b"".join(lines)
        # Each ends in its LF and holds no other: as many LFs as lines, each at an end.
        try:
            whole = data.count(b"\n") == len(lines) and _LF_ONLY.issuperset(map(_LAST_BYTE, lines))
        except IndexError:  # an empty line
            whole = False
        if not whole:
            for line in lines:
                _check_line(line)  # raises, saying which
        channel = Channel.CONTROL if control and self.dual else Channel.DATA
        return self._channels[channel].write(data)  # each is open (`_channel` falls back)

    def write_control(self, data: bytes) -> bool:
        """A whole encoded line on the control channel (or the only one)."""
        return self._write(Channel.CONTROL if self.dual else Channel.DATA, data)

    def write_realtime(self, data: bytes) -> bool:
        """A realtime byte on the control channel, ahead of every queued byte.

        With its LF (g2core swallows a terminator after a control character),
        or alone (grbl picks realtime bytes out of the stream wherever they
        are, and would answer an empty line `ok`).
        """
        if len(data) != 1:
            _check_line(data)
        return self._channel(Channel.CONTROL).write(data, urgent=True)

    def hand_over(self) -> None:
        """After a realtime byte the operator asked for: on a pseudo-terminal, give up
        the CPU once, so that the process at its other end reads the byte before the
        daemon goes on with what the byte set off (the hold's events, the notices).

        A pty's byte reaches that process only when a kernel worker and then the
        process get a CPU; on a small computer the daemon's own next half
        millisecond is often the CPU they wait for (docs/performance-log.md, "the CPU
        handed over after a `!`"). A USB device takes the byte in the write itself:
        nothing is given up for one.
        """
        if self._channel(Channel.CONTROL).pty:
            os.sched_yield()

    def _write(self, channel: Channel, data: bytes) -> bool:
        _check_line(data)
        return self._channel(channel).write(data)

    def write_backlog(self, channel: Channel = Channel.DATA) -> int:
        return self._channel(channel).write_backlog

    def _channel(self, channel: Channel) -> SerialChannel:
        return self._channels[channel if channel in self._channels else Channel.DATA]

    async def close(self) -> None:
        """Release every port (data first, the reverse of opening)."""
        for name in (Channel.DATA, Channel.CONTROL):
            if name in self._channels:
                await self._channels[name].close()


def _check_line(data: bytes) -> None:
    """Whole lines only: a realtime byte must never land inside a partial line."""
    if not data.endswith(b"\n") or b"\n" in data[:-1]:
        raise ValueError(f"not exactly one terminated line: {data!r}")
