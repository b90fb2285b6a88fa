"""The link over real pseudo-terminal pairs: lines both ways, loss as an event, no blocking."""

from __future__ import annotations

import asyncio
import os
import sys
from collections.abc import Iterator
from typing import Any

import pytest

from hostd.link import Channel, LineReceived, Link, LinkError, LinkLost
from hostd.link.link import INBOX_HIGH
from hostd.protocol.commands import Realtime, encode_line, encode_realtime
from tests.link.conftest import PtyPeer

pytestmark = pytest.mark.asyncio


async def read_lines(link: Link, count: int) -> list[LineReceived]:
    got: list[LineReceived] = []
    async with asyncio.timeout(2):
        while len(got) < count:
            for event in await link.read():
                assert isinstance(event, LineReceived), event
                got.append(event)
    return got


async def test_lines_from_the_device_arrive_in_order(peers: Iterator[PtyPeer]) -> None:
    peer = next(peers)
    link = await Link.open(str(peer.path))
    try:
        peer.write(b'{"r":{},"f":[1,0,4]}\n{"sr":{"stat":5}}\r\npartial')
        got = await read_lines(link, 2)
        assert [e.line for e in got] == [b'{"r":{},"f":[1,0,4]}', b'{"sr":{"stat":5}}']
        assert all(e.channel is Channel.DATA for e in got)
        peer.write(b" line\n")
        assert [e.line for e in await read_lines(link, 1)] == [b"partial line"]
    finally:
        await link.close()


async def test_lines_written_reach_the_device_exactly(peers: Iterator[PtyPeer]) -> None:
    peer = next(peers)
    link = await Link.open(str(peer.path))
    peer.start_reading()
    try:
        assert link.write_line(encode_line("G1 X10 F3000"))
        assert link.write_control(encode_realtime(Realtime.FEEDHOLD))
        await peer.wait_received(b"G1 X10 F3000\n!\n")
        assert bytes(peer.received) == b"G1 X10 F3000\n!\n"
    finally:
        await link.close()


async def test_only_whole_lines_can_be_written(peers: Iterator[PtyPeer]) -> None:
    peer = next(peers)
    link = await Link.open(str(peer.path))
    try:
        for bad in (b"G1 X1", b"!", b"G1\nG2\n"):
            with pytest.raises(ValueError):
                link.write_line(bad)
    finally:
        await link.close()


async def test_dual_port_routes_lines_to_data_and_realtime_to_control(
    peers: Iterator[PtyPeer],
) -> None:
    data, control = next(peers), next(peers)
    link = await Link.open(str(data.path), str(control.path))
    data.start_reading()
    control.start_reading()
    try:
        assert link.dual
        link.write_line(encode_line("G0 X1"))
        link.write_control(encode_realtime(Realtime.FEEDHOLD))
        link.write_control(b'{"sr":null}\n')
        await data.wait_received(b"G0 X1\n")
        await control.wait_received(b'!\n{"sr":null}\n')
        assert bytes(data.received) == b"G0 X1\n"
        assert bytes(control.received) == b'!\n{"sr":null}\n'
        control.write(b'{"r":{},"f":[1,0,1]}\n')
        (event,) = await read_lines(link, 1)
        assert event.channel is Channel.CONTROL
    finally:
        await link.close()


async def test_unplugged_device_is_a_lost_event_not_an_exception(
    peers: Iterator[PtyPeer],
) -> None:
    peer = next(peers)
    link = await Link.open(str(peer.path))
    try:
        peer.write(b"last words\n")
        await read_lines(link, 1)
        peer.unplug()
        async with asyncio.timeout(1):  # seen within 1 s
            events = await link.read()
        assert len(events) == 1 and isinstance(events[0], LinkLost)
        assert "disconnected" in events[0].reason
        assert link.lost is events[0]
        # Reading again keeps saying so; writing is refused quietly.
        assert await link.read() == [events[0]]
        assert link.write_line(b"G0 X1\n") is False
    finally:
        await link.close()


async def test_a_write_to_an_unplugged_device_is_refused_and_told_once(
    peers: Iterator[PtyPeer],
) -> None:
    """The write finds the loss before any read does: no exception, one lost event."""
    peer = next(peers)
    link = await Link.open(str(peer.path))
    try:
        peer.unplug()
        assert link.write_lines([b"G0 X1\n", b"G0 X2\n"]) is False
        assert link.write_realtime(b"!\n") is False
        async with asyncio.timeout(1):
            events = await link.read()
        assert len(events) == 1 and isinstance(events[0], LinkLost)
        assert "disconnected" in events[0].reason
        await asyncio.sleep(0.05)  # the read side sees the hang-up too: told no second time
        assert await link.read() == [events[0]]
    finally:
        await link.close()


async def test_lost_on_the_control_port_loses_the_link(peers: Iterator[PtyPeer]) -> None:
    data, control = next(peers), next(peers)
    link = await Link.open(str(data.path), str(control.path))
    try:
        control.unplug()
        async with asyncio.timeout(1):
            (event,) = await link.read()
        assert isinstance(event, LinkLost)
        assert event.channel is Channel.CONTROL
    finally:
        await link.close()


async def test_a_peer_that_stops_reading_never_blocks_the_loop(
    peers: Iterator[PtyPeer],
) -> None:
    """pyserial-asyncio-fast 0.16 spun inside write() here; then spammed the handler."""
    peer = next(peers)  # never reads until told to
    link = await Link.open(str(peer.path))
    loop = asyncio.get_running_loop()
    handler_calls: list[dict[str, Any]] = []
    loop.set_exception_handler(lambda _loop, ctx: handler_calls.append(ctx))
    try:
        ticks = 0

        async def ticker() -> None:
            nonlocal ticks
            while True:
                ticks += 1
                await asyncio.sleep(0)

        tick_task = asyncio.create_task(ticker())
        line = b"G1 X" + b"1" * 506 + b"\n"  # 512 bytes: fills a pty exactly
        for _ in range(200):  # 100 KB against a 17 KB kernel buffer
            assert link.write_line(line)
            await asyncio.sleep(0)
        assert link.write_backlog() > 0  # the rest waits in user space
        before = ticks
        await asyncio.sleep(0.01)
        assert ticks > before  # the loop keeps turning
        tick_task.cancel()

        peer.start_reading()  # the controller wakes up: everything arrives, in order
        await peer.wait_received(line * 200)
        assert bytes(peer.received) == line * 200
        assert link.write_backlog() == 0
        await asyncio.sleep(0.02)  # idle: a writer left registered would spin here
        assert handler_calls == []
    finally:
        loop.set_exception_handler(None)
        await link.close()


async def test_close_does_not_hang_on_unsent_bytes(peers: Iterator[PtyPeer]) -> None:
    peer = next(peers)
    link = await Link.open(str(peer.path))
    for _ in range(100):
        link.write_line(b"G1 X" + b"2" * 506 + b"\n")
    assert link.write_backlog() > 0
    async with asyncio.timeout(2):
        await link.close()


async def test_1200_baud_is_refused_before_anything_is_opened(
    peers: Iterator[PtyPeer],
) -> None:
    peer = next(peers)
    with pytest.raises(LinkError, match="1200"):
        await Link.open(str(peer.path), baudrate=1200)
    # The device was never touched: it can be opened normally.
    link = await Link.open(str(peer.path))
    await link.close()


async def test_a_port_is_opened_exclusively(peers: Iterator[PtyPeer]) -> None:
    peer = next(peers)
    link = await Link.open(str(peer.path))
    try:
        with pytest.raises(LinkError, match=str(peer.path)):
            await Link.open(str(peer.path))
    finally:
        await link.close()
    again = await Link.open(str(peer.path))  # released on close
    await again.close()


async def test_missing_device_is_a_clear_error(tmp_path: os.PathLike[str]) -> None:
    with pytest.raises(LinkError, match="no such device"):
        await Link.open(os.path.join(tmp_path, "ttyACM9"))


async def test_failed_second_port_releases_the_first(
    peers: Iterator[PtyPeer], tmp_path: os.PathLike[str]
) -> None:
    control = next(peers)
    with pytest.raises(LinkError):
        await Link.open(os.path.join(tmp_path, "missing"), str(control.path))
    link = await Link.open(str(control.path))  # not left locked
    await link.close()


async def test_runaway_output_is_cut_not_hoarded(peers: Iterator[PtyPeer]) -> None:
    peer = next(peers)
    link = await Link.open(str(peer.path))
    try:
        peer.write(b"x" * 10_000 + b"\nok\n")
        got = await read_lines(link, 2)
        assert [len(e.line) for e in got] == [4096, 2]
    finally:
        await link.close()


async def test_a_batch_of_lines_goes_out_in_order_as_one_write(peers: Iterator[PtyPeer]) -> None:
    peer = next(peers)
    link = await Link.open(str(peer.path))
    peer.start_reading()
    try:
        assert link.write_lines([b"G1 X1\n", b"G1 X2\n", b"G1 X3\n"])
        await peer.wait_received(b"G1 X1\nG1 X2\nG1 X3\n")
        for bad in (
            [b"G1 X4\n", b"G1 X5"],  # one line unterminated
            [b"G1 X4\nG1 X5\n", b"G1 X6\n"],  # two lines in one
            [b"G1 X4", b"\nG1 X5\n"],  # as many LFs as lines, in the wrong places
            [b"G1 X4"],  # alone, unterminated
            [b"G1 X4\nG1 X5\n"],  # alone, two lines in one
            [b"", b"G1 X4\n\n"],  # an empty line, and its LF on the next
        ):
            with pytest.raises(ValueError):
                link.write_lines(bad)
        assert link.write_lines([b"G1 X7\n"])  # nothing of the refused batches went before it
        await peer.wait_length(len(b"G1 X1\nG1 X2\nG1 X3\nG1 X7\n"))
        assert bytes(peer.received) == b"G1 X1\nG1 X2\nG1 X3\nG1 X7\n"
    finally:
        await link.close()


async def test_a_realtime_byte_overtakes_every_line_the_device_has_not_taken(
    peers: Iterator[PtyPeer],
) -> None:
    """A controller that stops reading: `!` must not wait behind 100 KB of queued lines."""
    peer = next(peers)  # never reads until told to
    link = await Link.open(str(peer.path))
    try:
        line = b"G1 X" + b"1" * 507 + b"\n"  # 512 bytes
        for _ in range(200):
            assert link.write_line(line)
        assert link.write_backlog() > 17 * 1024  # more than the kernel holds
        assert link.write_realtime(encode_realtime(Realtime.FEEDHOLD))
        peer.start_reading()
        total = len(line) * 200 + 2
        await peer.wait_length(total)
        got = bytes(peer.received)
        assert len(got) == total
        bang = got.index(b"!\n")
        # Ahead of all but what the kernel and the transport already held (whole lines).
        assert bang % len(line) == 0
        assert bang < 64 * len(line)  # the kernel holds some 17 to 21 KB; 200 lines is 100 KB
        assert got.replace(b"!\n", b"", 1) == line * 200  # the lines themselves, intact
    finally:
        await link.close()


_READS_IN_A_FRESH_PROCESS = """
import asyncio, os, resource
from hostd.link import Link

async def main():
    master, slave = os.openpty()
    got = asyncio.Event()

    class Receiver:
        def link_lines(self, channel, lines):
            got.set()

        def link_lost(self, reason):
            raise AssertionError(reason)

    link = await Link.open(os.ttyname(slave), receiver=Receiver())
    for warm_up in (True, False):
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        for _ in range(50 if warm_up else 500):
            got.clear()
            os.write(master, b"ok\\n")
            await got.wait()
    print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    await link.close()

asyncio.run(main())
"""


async def test_a_read_costs_no_fresh_memory_in_a_young_daemon() -> None:
    """serialx reads up to 256 KiB a read; glibc serves that from a fresh mmap until the
    process has freed a larger block, so each read of a 3-byte `ok` cost a mapping and
    its page faults (2 a read, 1,000 for 500 reads, measured). The link reads at most
    64 KiB, from the heap: a daemon just started pays no page fault a read. Run in a
    fresh interpreter, whose allocator has its first threshold."""
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-c",
        _READS_IN_A_FRESH_PROCESS,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    async with asyncio.timeout(60):
        out, err = await process.communicate()
    assert process.returncode == 0, err.decode()
    assert int(out) < 100, out  # page faults in 500 reads


async def test_a_pty_link_hands_the_cpu_over_once_and_a_device_that_is_none_never(
    peers: Iterator[PtyPeer], monkeypatch: pytest.MonkeyPatch
) -> None:
    """`hand_over` gives the CPU up once on a pseudo-terminal (a process is its other end)
    and never on anything else: a USB device takes the byte in the write itself."""
    from hostd.link import serial

    yields: list[None] = []
    monkeypatch.setattr(os, "sched_yield", lambda: yields.append(None))
    peer = next(peers)
    link = await Link.open(str(peer.path))
    try:
        assert link.write_realtime(b"!\n")
        link.hand_over()
        assert yields == [None]
        peer.start_reading()
        await peer.wait_received(b"!\n")
    finally:
        await link.close()
    read, write = os.pipe()
    null = os.open(os.devnull, os.O_RDWR)
    try:
        assert not serial._is_pty(null) and not serial._is_pty(read)
        assert peer.master is not None and serial._is_pty(peer.master)
    finally:
        for fd in (read, write, null):
            os.close(fd)


async def test_an_unread_inbox_stops_the_reading_and_loses_no_line(
    peers: Iterator[PtyPeer],
) -> None:
    """A device that floods a link nobody reads: past INBOX_HIGH lines the channel stops
    reading its descriptor (the rest waits in the kernel, the device's writes stall),
    and once read again every line arrives, in order, none lost or cut."""
    peer = next(peers)
    link = await Link.open(str(peer.path))
    loop = asyncio.get_running_loop()
    lines = [b"%06d" % i + b"x" * 90 for i in range(INBOX_HIGH * 3)]
    data = memoryview(b"".join(line + b"\n" for line in lines))
    assert peer.master is not None
    master = peer.master

    def write_more() -> None:  # as fast as the pty takes them
        nonlocal data
        data = data[os.write(master, data) :]
        if not data:
            loop.remove_writer(master)

    loop.add_writer(master, write_more)
    try:
        async with asyncio.timeout(5):
            while not link._paused:  # set in the read that brought the inbox to INBOX_HIGH
                link._wakeup.clear()
                await link._wakeup.wait()
        # A hundred turns of the loop, the device's bytes waiting in the kernel at each:
        # a reader still registered would take them, one read a turn.
        for _ in range(100):
            await asyncio.sleep(0)
        assert data, "the device wrote everything: nothing held it back"
        assert INBOX_HIGH <= len(link._inbox) < INBOX_HIGH + 700  # one read's lines more
        got = await read_lines(link, len(lines))
        assert [event.line for event in got] == lines
    finally:
        loop.remove_writer(master)
        await link.close()
