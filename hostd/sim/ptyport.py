"""One simulated USB serial port: a pseudo-terminal pair behind a stable symlink.

The board side holds the pty master; the host opens the slave through the
symlink, as it would open a /dev/serial/by-id link. What this file knows
about Linux ptys (measured, see ../shared/notes/python-stack.md section 2):

- The slave is put in raw mode at once and our copy of it closed: while any
  slave fd is open the master never sees the host hang up.
- In packet mode (TIOCPKT) every master read is one packet: a zero byte then
  data, or a single status byte; a host's tcflush (serialx ends its open
  with TCIOFLUSH) arrives as a status byte with the flush bits set.
  TCIOFLUSH sets its two bits one after the other (FLUSHREAD: the host's
  input was discarded; then FLUSHWRITE: what it wrote and we did not read),
  so a master that reads in between sees them as two packets. The bits are
  OR-ed into one status byte that a read clears: a bit comes again only
  from another flush, which any host may make at any time (Python's
  `tty.setraw` flushes with TCSAFLUSH, pyserial's reset_input_buffer): a
  flush bit says nothing about opens.
- Opens are counted with inotify on the slave device: each open(2) is an
  IN_OPEN, each last close of it an IN_CLOSE_*, queued as the syscall runs.
  The master cannot see a host that closed and opened again before it read
  (no EIO in between), but the count went to zero and back: a reopen.
- FIONREAD on a slave fd counts what the host has not read yet: a fd of our
  own, opened for a moment, tells whether bytes we wrote survived a flush.
  What we write waits in the tty's flip buffer until a kernel worker moves
  it to the read queue that FIONREAD counts; a poll on the slave moves it
  at once (n_tty_poll), so we poll before we ask.
- While no host has the slave open the master polls POLLHUP and reads EIO.
  Registering it with the event loop then would spin, so attachment is
  polled with a short timer, and the reader is added only once a host is
  there. A host closing shows as EIO (after any data it wrote).
- The pty buffers about 17 KB each way: when the host stops reading, our
  writes are kept in a backlog and finished when it reads again.

Unplugging closes the master and removes the symlink, so the host reads
EOF/EIO; plugging again makes a new pair and atomically replaces the link.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import errno
import fcntl
import os
import select
import struct
import termios
import tty
from typing import Protocol

import structlog

log = structlog.get_logger(__name__)

ATTACH_POLL = 0.005  # s between looks at the master while no reader is registered
FLUSHREAD, FLUSHWRITE = 0x01, 0x02  # TIOCPKT_FLUSHREAD, TIOCPKT_FLUSHWRITE
_FLUSH_BITS = FLUSHREAD | FLUSHWRITE
IN_OPEN, IN_CLOSE_WRITE, IN_CLOSE_NOWRITE = 0x20, 0x08, 0x10  # <sys/inotify.h>
_EVENT = struct.Struct("iIII")  # wd, mask, cookie, len (then len bytes of name)
_libc = ctypes.CDLL(None, use_errno=True)


class PortListener(Protocol):
    """What a port reports to its board (all called from the event loop)."""

    def port_attached(self, port: PtyPort) -> None: ...
    def port_detached(self, port: PtyPort) -> None: ...
    def port_flushed(self, port: PtyPort) -> None: ...  # which bits: `port.flush_bits`
    def port_data(self, port: PtyPort, data: bytes) -> None: ...
    def port_drained(self, port: PtyPort) -> None: ...


class PtyPort:
    """A pty master whose slave is reachable at `path`; `name` is its configured name."""

    def __init__(self, name: str, path: str, listener: PortListener) -> None:
        self.name = name
        self.path = path
        self._listener = listener
        self._loop = asyncio.get_running_loop()
        self._fd: int | None = None
        self._tty: str | None = None
        self._poller: select.poll | None = None
        self._poll_handle: asyncio.TimerHandle | None = None
        self._reader_on = False
        self._writer_on = False
        self._read_limit = 0
        self._backlog = bytearray()
        self.written = 0  # bytes the pty has taken from us, ever
        self.flush_bits = 0  # the flush bits of the status packet last read
        self.attached = False
        self._watch: int | None = None  # inotify on the slave: the host's opens and closes
        self._opens = 0  # slave fds the hosts hold (ours not counted)
        self._reopened = False  # that count went to 0 and back since we attached
        self._own_opens = self._own_closes = 0  # our own (`unread`), not to be counted

    @property
    def plugged(self) -> bool:
        return self._fd is not None

    @property
    def tty_name(self) -> str | None:
        """The slave device the symlink points at (None while unplugged)."""
        return self._tty

    @property
    def backlog(self) -> int:
        """Bytes written that the host has not taken yet."""
        return len(self._backlog)

    def unread(self) -> int:
        """Bytes the pty holds that the host has not read (its input queue)."""
        if self._tty is None:
            return 0
        self._drain_watch()  # the hosts' events before ours, so that ours are ours
        try:
            fd = os.open(self._tty, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError:
            return 0
        self._own_opens += 1  # its IN_OPEN and IN_CLOSE_NOWRITE are not a host's
        self._own_closes += 1
        try:
            poller = select.poll()
            poller.register(fd, select.POLLIN)
            poller.poll(0)  # moves what we wrote from the flip buffer to the read queue
            (count,) = struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))
        except OSError:
            count = 0
        finally:
            os.close(fd)
        return int(count)

    def take_flush(self) -> bool:
        """Read a flush the host made and we have not read yet, now; True if there was one.

        Status is polled as POLLPRI and read ahead of any data (n_tty_read), so
        this never takes the host's bytes.
        """
        poller = self._poller
        if poller is None or not self.attached:
            return False
        if not any(ev & select.POLLPRI for _, ev in poller.poll(0)):
            return False
        self._on_readable(status_only=True)
        return True

    # --- plugging

    def plug(self) -> None:
        """Create the pty pair and point the symlink at its slave."""
        if self._fd is not None:
            return
        master, slave = os.openpty()
        try:
            tty.setraw(slave)
            name = os.ttyname(slave)
        finally:
            os.close(slave)
        try:
            fcntl.ioctl(master, termios.TIOCPKT, struct.pack("i", 1))
            os.set_blocking(master, False)
            _replace_symlink(name, self.path)
        except BaseException:
            os.close(master)
            raise
        self._fd, self._tty = master, name
        self._watch = _watch_opens(name)
        self._opens = self._own_opens = self._own_closes = 0
        self._reopened = False
        self._poller = select.poll()
        self._poller.register(master, select.POLLIN | select.POLLPRI)
        self._refresh()
        log.debug("sim port plugged", port=self.name, path=self.path, tty=name)

    def unplug(self) -> None:
        """Close the master (the host reads EOF/EIO) and remove the symlink."""
        fd = self._fd
        if fd is None:
            return
        was_attached = self.attached
        self._stop_io()
        self._fd = None
        self._poller = None
        self.attached = False
        os.close(fd)
        if self._watch is not None:
            os.close(self._watch)
            self._watch = None
        with contextlib.suppress(OSError):
            if os.readlink(self.path) == self._tty:
                os.unlink(self.path)
        log.debug("sim port unplugged", port=self.name, path=self.path)
        self._tty = None
        if was_attached:
            self._listener.port_detached(self)

    # --- reading

    def set_read_limit(self, limit: int) -> None:
        """Take at most `limit` more bytes from the host for now; 0 stops reading."""
        self._read_limit = max(limit, 0)
        self._refresh()

    def _refresh(self) -> None:
        fd = self._fd
        if fd is None:
            return
        want = self.attached and self._read_limit > 0
        if want and not self._reader_on:
            self._loop.add_reader(fd, self._on_readable)
            self._reader_on = True
        elif not want and self._reader_on:
            self._loop.remove_reader(fd)
            self._reader_on = False
        if not want and self._poll_handle is None:
            # Not reading: poll for the host opening (or, if attached, closing).
            self._poll_handle = self._loop.call_later(ATTACH_POLL, self._poll)

    def _poll(self) -> None:
        self._poll_handle = None
        if self._poller is None:
            return
        hangup = any(ev & select.POLLHUP for _, ev in self._poller.poll(0))
        if not self.attached and not hangup:
            self._drain_watch()  # the opens up to this one are this attachment
            self._reopened = False
            self.attached = True
            log.debug("sim port opened by host", port=self.name)
            self._listener.port_attached(self)
        elif self.attached and hangup:
            self._detach()
            return
        self._refresh()

    def read_waiting(self) -> None:
        """Take now what the host has written and this port has not read yet.

        A board's receive interrupt takes bytes as they arrive, whatever its main
        loop is doing; this port's reader runs only when the event loop gets round
        to it. The board's loop calls this before it runs what is due, so that a
        board whose move ended never finds its planner empty, and stops, with the
        host's next lines already written to it (a host on time taken for a late one:
        an underflow that no real board would have).
        """
        poller = self._poller
        if poller is None or not self._reader_on:
            return
        if any(events & select.POLLIN for _, events in poller.poll(0)):
            self._on_readable()

    def _on_readable(self, status_only: bool = False) -> None:
        fd = self._fd
        if fd is None:
            return
        try:
            packet = os.read(fd, 1 if status_only else self._read_limit + 1)
        except BlockingIOError:
            return
        except OSError as exc:
            if exc.errno != errno.EIO:
                log.warning("sim port read failed", port=self.name, error=str(exc))
            self._detach()
            return
        if not packet:
            self._detach()
            return
        if packet[0] == 0:
            if len(packet) > 1:
                self._read_limit = max(self._read_limit - (len(packet) - 1), 0)
                self._listener.port_data(self, packet[1:])
        elif packet[0] & _FLUSH_BITS:
            # The opener flushes after its open(2), whose IN_OPEN is queued by then:
            # a host that closed and opened again unseen is a new open before this flush.
            self._drain_watch()
            if self._reopened:
                self._reopened = False
                log.debug("sim port reopened by host", port=self.name)
                self._listener.port_detached(self)
                if self.attached:
                    self._listener.port_attached(self)
            if self.attached:
                self.flush_bits = packet[0] & _FLUSH_BITS
                self._listener.port_flushed(self)

    def _drain_watch(self) -> None:
        """Count the hosts' opens and closes queued so far; a count back from 0 is a reopen."""
        watch = self._watch
        while watch is not None:
            try:
                events = os.read(watch, 4096)
            except BlockingIOError:
                return
            except OSError:
                return
            at = 0
            while at + _EVENT.size <= len(events):
                _, mask, _, length = _EVENT.unpack_from(events, at)
                at += _EVENT.size + length
                if mask & IN_OPEN and self._own_opens:
                    self._own_opens -= 1
                elif mask & IN_OPEN:
                    self._opens += 1
                    if self._opens == 1 and self.attached:
                        self._reopened = True
                elif mask & IN_CLOSE_NOWRITE and self._own_closes:
                    self._own_closes -= 1
                elif mask & (IN_CLOSE_WRITE | IN_CLOSE_NOWRITE):
                    self._opens = max(self._opens - 1, 0)

    def _detach(self) -> None:
        self._stop_io()
        self._drain_watch()
        self._reopened = False
        self.attached = False
        log.debug("sim port closed by host", port=self.name)
        self._listener.port_detached(self)
        self._refresh()

    # --- writing

    def write(self, data: bytes) -> bool:
        """Send bytes to the host; False if no host has the port open."""
        fd = self._fd
        if fd is None or not self.attached:
            return False
        if self._backlog:
            self._backlog += data
            return True
        try:
            written = os.write(fd, data)
        except BlockingIOError:
            written = 0
        except OSError:
            return False  # the host just went; the reader or the poll will notice
        self.written += written
        if written < len(data):
            self._backlog += data[written:]
            self._loop.add_writer(fd, self._on_writable)
            self._writer_on = True
        return True

    def _on_writable(self) -> None:
        fd = self._fd
        if fd is None:
            return
        try:
            written = os.write(fd, self._backlog)
        except BlockingIOError:
            return
        except OSError:
            written = len(self._backlog)
        self.written += written
        del self._backlog[:written]
        if not self._backlog:
            self._loop.remove_writer(fd)
            self._writer_on = False
            self._listener.port_drained(self)

    def _stop_io(self) -> None:
        fd = self._fd
        if self._poll_handle is not None:
            self._poll_handle.cancel()
            self._poll_handle = None
        if fd is not None and self._reader_on:
            self._loop.remove_reader(fd)
        if fd is not None and self._writer_on:
            self._loop.remove_writer(fd)
        self._reader_on = self._writer_on = False
        self._backlog.clear()


def _watch_opens(tty_path: str) -> int | None:
    """An inotify fd reporting each open and last close of the slave (None if refused)."""
    fd = int(_libc.inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC))
    if fd < 0:
        log.warning("sim port cannot watch opens", error=os.strerror(ctypes.get_errno()))
        return None
    mask = IN_OPEN | IN_CLOSE_WRITE | IN_CLOSE_NOWRITE
    if int(_libc.inotify_add_watch(fd, tty_path.encode(), mask)) < 0:
        log.warning("sim port cannot watch opens", error=os.strerror(ctypes.get_errno()))
        os.close(fd)
        return None
    return fd


def _replace_symlink(target: str, path: str) -> None:
    """Point `path` at `target` in one step, as udev does when a device comes back."""
    tmp = f"{path}.{os.getpid()}.tmp"
    with contextlib.suppress(FileNotFoundError):
        os.unlink(tmp)
    os.symlink(target, tmp)
    os.replace(tmp, path)
