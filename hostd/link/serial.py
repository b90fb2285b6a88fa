"""One serial channel: a device opened exclusively, in raw mode, moving lines.

The serial library is chosen here and nowhere else. It is serialx, Home
Assistant's maintained successor of pyserial-asyncio: its writes are eager
(no loop iteration of delay for a realtime byte), EAGAIN is "0 bytes
written" rather than a busy loop, it opens and closes off the event loop,
and it passed every write-path test in ../shared/notes/python-stack.md
where pyserial-asyncio-fast 0.16 spun at 100% CPU after a partial write and
blocked the loop when the peer stopped reading (tests/link pins both cases).

Failures of the device while open (EOF, EIO, unplug) never surface as an
exception: the channel reports them once, as a `lost` callback.

Realtime never waits behind the daemon's own bytes. The transport is given
bytes only while its buffer is empty (its high-water mark is 0, so it says
`pause_writing` the moment the device stops taking them); what the device
has not taken yet waits here, in two queues, and urgent bytes (`!`, `~`,
0x18...) leave before any line queued beside them. Whatever the transport
already holds is at most the tail of one write, whole lines, so an urgent
byte never lands inside a partial line.

While the transport holds nothing, bytes are written to the port's descriptor
here, as serialx's own `write` would write them first (one `os.write`, the
rest, if the device took only part, handed to the transport to hold). That is
the same system call with seven Python calls fewer (serialx's checks and its
debug logging) on every write: every `!` and every batch of a job's lines
(docs/performance-log.md, "the port written directly").

The descriptor is read here too: the channel's own reader replaces serialx's
on the event loop once the port is open (`connection_made`), and reads as
serialx's would (one `os.read` of up to READ_SIZE; EAGAIN is nothing to
read; 0 bytes or an error is the device gone), without its two debug calls a
read (docs/performance-log.md, "the express step as one call"). serialx still
opens, configures and closes the port, and removes the reader when it closes
the descriptor.
"""

from __future__ import annotations

import asyncio
import errno
import os
import stat
from collections import deque
from collections.abc import Callable

import serialx
from serialx.common import SerialException

from hostd.protocol.framing import LineBuffer

# The 1200-baud "touch" resets native-USB boards into their bootloader, and
# on some boards that erases the firmware (g2core.md section 1).
BOOTLOADER_BAUD = 1200
_CLOSE_GRACE = 1.0
READ_SIZE = 64 * 1024  # bytes a read takes at most (`connection_made`)
# Pseudo-terminals (the kernel's Documentation/admin-guide/devices.txt): the BSD
# masters and slaves (majors 2, 3), Unix98's (128-135, 136-143), and a master
# opened through /dev/ptmx (5, 2).
_PTY_MAJORS = frozenset((2, 3, *range(128, 144)))
_PTMX = (5, 2)


class LinkError(Exception):
    """A port could not be opened; the message says which and why."""


LineSink = Callable[[list[bytes]], None]  # every line one read completed, in order
LostSink = Callable[[str], None]


class SerialChannel(asyncio.Protocol):
    """A device path opened through serialx, split into lines with `LineBuffer`."""

    def __init__(self, path: str, on_lines: LineSink, on_lost: LostSink) -> None:
        self.path = path
        self._on_lines = on_lines
        self._on_lost = on_lost
        self._framer = LineBuffer()
        self._transport: asyncio.Transport | None = None
        self._closed = asyncio.get_running_loop().create_future()
        self.lost = False
        self._blocked = False  # the transport holds bytes the device has not taken
        self._urgent: deque[bytes] = deque()
        self._queued: deque[bytes] = deque()
        self._queued_bytes = 0
        self._fd = -1  # the port's descriptor, serialx's: read here, and written while its
        # transport holds nothing
        self._loop = asyncio.get_running_loop()
        # The device is a pseudo-terminal: a process on this computer is the other end (a
        # simulated board, socat, ser2net), and reads a byte only once it has a CPU.
        self.pty = False

    @classmethod
    async def open(
        cls, path: str, baudrate: int, on_lines: LineSink, on_lost: LostSink
    ) -> SerialChannel:
        if baudrate == BOOTLOADER_BAUD:
            raise LinkError(f"{path}: refusing {BOOTLOADER_BAUD} baud, the bootloader touch")
        channel = cls(path, on_lines, on_lost)
        loop = asyncio.get_running_loop()
        try:
            await serialx.create_serial_connection(
                loop, lambda: channel, url=path, baudrate=baudrate, exclusive=True
            )
        except FileNotFoundError as exc:
            raise LinkError(f"{path}: no such device") from exc
        except (OSError, SerialException) as exc:
            raise LinkError(f"{path}: cannot open: {_describe(exc)}") from exc
        return channel

    # asyncio.Protocol

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self._transport = transport
        transport.set_write_buffer_limits(high=0, low=0)
        self._fd = transport.get_extra_info("serial").fileno()
        self.pty = _is_pty(self._fd)
        # serialx reads up to 256 KiB a read (`DescriptorTransport.max_size`). glibc
        # serves a buffer that size with mmap (its threshold starts at 128 KiB and only
        # rises when a larger mmapped block is freed), and CPython shrinks it to the bytes
        # read with mremap: three system calls and a page fault a read, in a daemon young
        # enough never to have freed a large block. 64 KiB is under the threshold, and
        # more than a board's serial line delivers between two reads.
        transport.max_size = READ_SIZE  # type: ignore[attr-defined]
        self._loop.add_reader(self._fd, self._read_ready)  # in place of serialx's

    def _read_ready(self) -> None:
        """The port has bytes (or is gone): one read, its lines to the link."""
        try:
            data = os.read(self._fd, READ_SIZE)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._fail(exc)
            return
        if not data:
            # A hung-up tty reads 0 bytes (drivers/tty/tty_io.c, hung_up_tty_read): the
            # device is gone, as the EIO its writes get says.
            self._fail(OSError(errno.EIO, "device disconnected"))
            return
        lines = self._framer.feed(data)
        if lines:
            self._on_lines(lines)

    def data_received(self, data: bytes) -> None:
        # asyncio.Protocol's: only serialx's reader calls it, and `connection_made` puts
        # `_read_ready` in its place before the loop turns. Kept so that a serialx that
        # read before `connection_made` would hand its bytes on, not drop them.
        lines = self._framer.feed(data)
        if lines:
            self._on_lines(lines)

    def connection_lost(self, exc: Exception | None) -> None:
        if not self._closed.done():
            self._closed.set_result(None)
        self._report_lost(_describe(exc) if exc else "closed")

    def set_reading(self, on: bool) -> None:
        """Stop or restart taking bytes from the device (backpressure)."""
        transport = self._transport
        if transport is not None and not transport.is_closing():
            if on:
                self._loop.add_reader(self._fd, self._read_ready)
            else:
                self._loop.remove_reader(self._fd)

    # writing

    def write(self, data: bytes, *, urgent: bool = False) -> bool:
        """Write bytes, or queue them while the device is not taking any.

        Urgent bytes go ahead of every queued one. False if the channel is
        gone (the lost report says why).
        """
        if self.lost or self._transport is None:
            return False
        if not self._blocked:
            return self._send(data)
        if urgent:
            self._urgent.append(data)
        else:
            self._queued.append(data)
            self._queued_bytes += len(data)
        return True

    def pause_writing(self) -> None:
        self._blocked = True

    def resume_writing(self) -> None:
        """The device took everything: hand it what waited, urgent bytes first."""
        self._blocked = False
        while not self._blocked and (self._urgent or self._queued):
            if self._urgent:
                data = b"".join(self._urgent)
                self._urgent.clear()
            else:
                data = b"".join(self._queued)
                self._queued.clear()
                self._queued_bytes = 0
            if not self._send(data):
                return

    def _send(self, data: bytes) -> bool:
        """Write now what the device takes; the transport holds the rest (and then says
        `pause_writing`). Called only while it holds nothing (`_blocked` is False)."""
        transport = self._transport
        assert transport is not None
        try:
            if transport.is_closing():
                written = 0  # serialx tells what a write to a closing port means
            else:
                try:
                    written = os.write(self._fd, data)
                except (BlockingIOError, InterruptedError):
                    written = 0
            if written < len(data):
                transport.write(data[written:] if written else data)
        except (OSError, SerialException) as exc:
            self._fail(exc)
            return False
        return not self.lost

    def _fail(self, exc: Exception) -> None:
        """The device failed a read or a write: reported lost, the port closed."""
        self._report_lost(_describe(exc))
        if self._transport is not None:
            self._transport.abort()

    @property
    def write_backlog(self) -> int:
        """Bytes accepted but not yet taken by the device (it may have stopped reading)."""
        held = self._queued_bytes + sum(map(len, self._urgent))
        return held + (self._transport.get_write_buffer_size() if self._transport else 0)

    # closing

    async def close(self) -> None:
        """Close and wait until the device is released; unsent bytes are dropped."""
        self.lost = True  # asked for: no lost report
        transport = self._transport
        if transport is not None and not self._closed.done():
            if transport.get_write_buffer_size():
                transport.abort()  # a peer that stopped reading would hold close() forever
            else:
                transport.close()
            done, _ = await asyncio.wait({self._closed}, timeout=_CLOSE_GRACE)
            if not done:
                transport.abort()
                await self._closed

    def _report_lost(self, reason: str) -> None:
        if not self.lost:
            self.lost = True
            self._on_lost(reason)


def _describe(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.errno is not None:
        if exc.errno == errno.EIO:
            return "device disconnected (I/O error)"
        return f"{os.strerror(exc.errno)} (errno {exc.errno})"
    return str(exc) or type(exc).__name__


def _is_pty(fd: int) -> bool:
    """The descriptor is a pseudo-terminal's (either end)."""
    mode = os.fstat(fd)
    if not stat.S_ISCHR(mode.st_mode):
        return False
    major, minor = os.major(mode.st_rdev), os.minor(mode.st_rdev)
    return major in _PTY_MAJORS or (major, minor) == _PTMX
