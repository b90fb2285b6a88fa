"""The board as a device: opening, banners, dual ports, unplug, reset, backpressure."""

from __future__ import annotations

import asyncio
import os
import select
import signal
import sys
import termios
from pathlib import Path

import pytest

from hostd.protocol.states import MachineState
from hostd.sim import Received, SimConfig, SimController
from hostd.sim.ptyport import PtyPort

from .conftest import INSTANT, Host, RawHost, dual, is_link

pytestmark = pytest.mark.asyncio


def banners(sim: SimController) -> int:
    return sum(b"SYSTEM READY" in s.data for s in sim.sent)


async def test_one_banner_per_open_and_another_after_reopening(sim: SimController) -> None:
    host = await Host.open(sim.data_path)
    assert (await host.ask(b"{xvm:n}\n"))["f"] == [1, 0, 9]  # no second banner before it
    await host.close()
    await sim.wait_for(lambda: not sim.attached())
    host = await Host.open(sim.data_path)
    try:
        assert (await host.ask(b"{xvm:n}\n"))["f"] == [1, 0, 9]
        assert banners(sim) == 2
    finally:
        await host.close()


async def more_banners(host: Host) -> int:
    """Ask `{xvm:n}`: how many more banners the host reads before the answer.

    What the host gets is what counts: an opener slow to flush (a loaded machine
    runs serialx's open late) throws the board's first banner away, and the board
    sends it again (`test_a_fallback_banner_the_flush_threw_away_is_sent_again`).
    """
    host.send(b"{xvm:n}\n")
    got = await host.until(lambda m: "xvm" in m.get("r", {}))
    return sum(m.get("r", {}).get("msg") == "SYSTEM READY" for m in got)


async def test_a_host_reopening_at_once_still_gets_a_banner_each_time(
    sim: SimController,
) -> None:
    for _ in range(20):  # faster than the board may notice the close in between
        host = await Host.open(sim.data_path)  # its first line is the banner
        try:
            assert await more_banners(host) == 0
        finally:
            await host.close()


async def test_an_opener_that_does_not_flush_still_gets_its_banner(sim: SimController) -> None:
    raw = RawHost(sim.data_path)
    try:
        banner = await raw.message()
        assert banner["r"]["msg"] == "SYSTEM READY"
        assert banner["f"] == [1, 0, 1]
        assert banner["r"]["fb"] == 101.06
    finally:
        raw.close()


async def test_a_tinyg_build_number_gives_a_tinyg_banner(tmp_path: Path) -> None:
    config = SimConfig(instant=True, fb=440.21)
    async with SimController(str(tmp_path / "tty"), config=config) as sim:
        host = await Host.open(sim.data_path, banner=False)
        try:
            banner = await host.message()
            assert banner["r"]["fb"] == 440.21
            assert len(banner["f"]) == 4
        finally:
            await host.close()


async def test_dual_port_output_goes_only_to_the_port_opened_first(tmp_path: Path) -> None:
    async with dual(tmp_path, INSTANT) as (sim, control, data):
        data.write(b"G0 X1\n{yvm:n}\n")
        first = await control.response()
        second = await control.response()
        assert {first["f"][2], second["f"][2]} == {6, 9}  # both answered on control
        assert (await control.ask(b"{xvm:n}\n"))["r"] == {"xvm": 6000}
        assert data.pending() == b""  # the data port never receives anything
        assert {s.port for s in sim.sent} == {"control"}
        assert {(r.port, r.data) for r in sim.received} == {
            ("data", b"G0 X1"),
            ("data", b"{yvm:n}"),
            ("control", b"{xvm:n}"),
        }


async def test_roles_follow_open_order_not_port_names(tmp_path: Path) -> None:
    async with SimController(
        str(tmp_path / "data"), control_path=str(tmp_path / "ctrl"), config=INSTANT
    ) as sim:
        assert sim.control_path is not None
        first = await Host.open(sim.data_path)
        second = RawHost(sim.control_path)
        try:
            await sim.wait_attached(port="control")
            second.write(b"{xvm:n}\n")
            assert (await first.response())["r"] == {"xvm": 6000}
            assert second.pending() == b""
        finally:
            second.close()
            await first.close()


async def test_unplug_is_seen_by_the_host_and_replug_brings_a_banner(
    sim: SimController, host: Host
) -> None:
    await sim.unplug()
    await host.hangup()
    assert not is_link(sim.data_path)
    await host.close()
    await sim.replug()
    assert is_link(sim.data_path)
    again = await Host.open(sim.data_path)
    try:
        assert (await again.ask(b"{xvm:n}\n"))["r"] == {"xvm": 6000}
    finally:
        await again.close()


async def test_reset_reboots_the_board_with_fresh_state(sim: SimController, host: Host) -> None:
    sim.set_homed(True)
    await host.ask(b"G0 X5\n")
    host.send(b"\x18")
    await host.hangup()
    await host.close()
    await sim.wait_for(lambda: is_link(sim.data_path))
    assert sim.state == MachineState.READY
    assert not sim.homed
    assert sim.position["x"] == 0
    again = await Host.open(sim.data_path)  # a banner first, and only one
    assert await more_banners(again) == 0
    await again.close()
    await sim.reset()  # the same from the test's side
    again = await Host.open(sim.data_path)
    assert await more_banners(again) == 0
    await again.close()


async def test_stopping_reading_backs_up_the_hosts_writes(sim: SimController, host: Host) -> None:
    sim.stop_reading()
    host.send(b"\n" * 65536)  # empty lines: the board will answer nothing
    assert host.writer.transport.get_write_buffer_size() > 0
    sim.resume_reading()
    async with asyncio.timeout(5):
        await host.writer.drain()
    assert (await host.ask(b"$xvm\n"))["r"] == {"xvm": 6000}


async def test_a_plain_writer_sees_eagain_while_the_board_does_not_read(
    sim: SimController,
) -> None:
    raw = RawHost(sim.data_path)
    try:
        await raw.message()
        sim.stop_reading()
        with pytest.raises(BlockingIOError):
            for _ in range(1000):
                raw.write(b"\n" * 512)
        sim.resume_reading()
        await raw.writable()
        raw.write(b"$xvm\n")
        assert (await raw.message())["r"] == {"xvm": 6000}
    finally:
        raw.close()


async def test_the_rx_budget_stops_reading_when_the_planner_is_full(tmp_path: Path) -> None:
    config = SimConfig(planner_depth=1, rx_budget=256)
    async with SimController(str(tmp_path / "tty"), config=config) as sim:
        host = await Host.open(sim.data_path)
        try:
            host.send(b"G1 X10 F60\n")  # ten seconds: the planner stays full
            line = b"G1 Y1 (padding padding padding)\n"
            host.send(line * 100)
            await sim.wait_for(lambda: len(sim.received) > 256 // len(line))
            got = sum(len(r.data) + 1 for r in sim.received[1:])
            assert got <= 256
        finally:
            await host.close()


async def test_garbage_arrives_raw(sim: SimController, host: Host) -> None:
    garbage = b'\xff\xfe\x00{"r":{"x"\n'
    sim.inject_garbage(garbage)
    assert await host.line() == garbage[:-1]
    assert sim.sent[-1] == Received(sim.sent[-1].t, "data", garbage, "raw")


async def test_a_silent_board_answers_nothing_until_it_wakes(
    sim: SimController, host: Host
) -> None:
    sim.go_silent(True)
    host.send(b"$xvm\n")
    assert b"$xvm" not in [r.data for r in sim.received]  # a hung board reads nothing
    sim.go_silent(False)
    assert (await host.response())["r"] == {"xvm": 6000}


async def test_received_records_exact_bytes_kinds_and_ports(sim: SimController, host: Host) -> None:
    host.send(b"G0 X1\r\n!\r{sr:n}\n\x05")
    await sim.wait_for(lambda: len(sim.received) == 4)
    assert [(r.port, r.data, r.kind) for r in sim.received] == [
        ("data", b"G0 X1", "line"),
        ("data", b"!", "realtime"),
        ("data", b"{sr:n}", "line"),
        ("data", b"\x05", "realtime"),
    ]
    times = [r.t for r in sim.received]
    assert times == sorted(times)


async def test_closing_the_simulator_leaves_no_descriptors_or_links(tmp_path: Path) -> None:
    before = set(os.listdir("/proc/self/fd"))
    sim = SimController(str(tmp_path / "a"), control_path=str(tmp_path / "b"), config=INSTANT)
    await sim.start()
    host = await Host.open(sim.data_path)
    host.send(b"\x18")
    await host.hangup()
    await host.close()
    await sim.close()
    assert set(os.listdir("/proc/self/fd")) <= before
    assert not is_link(tmp_path / "a")
    assert not is_link(tmp_path / "b")


async def test_the_simulator_runs_standalone(tmp_path: Path) -> None:
    path = str(tmp_path / "tty")
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "hostd.sim",
        "--data",
        path,
        "--instant",
        stdout=asyncio.subprocess.PIPE,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)},
    )
    try:
        assert proc.stdout is not None
        async with asyncio.timeout(10):
            printed = await proc.stdout.readline()
        assert printed.decode().split() == ["data", path]
        host = await Host.open(path)
        try:
            assert (await host.ask(b"{stat:n}\n"))["r"] == {"stat": 1}
        finally:
            await host.close()
    finally:
        proc.send_signal(signal.SIGTERM)
        async with asyncio.timeout(10):
            assert await proc.wait() == 0
    assert not is_link(path)


async def banners_before_answer(raw: RawHost, sim: SimController) -> int:
    """Ask `{xvm:n}` and read up to its answer: how many banners the host got.

    The board reads a pending flush before any data, so once it has read the
    line it has seen every flush: only then does the host read.
    """
    raw.write(b"{xvm:n}\n")
    await sim.wait_received(b"{xvm:n}")
    count = 0
    while "xvm" not in (message := await raw.message()).get("r", {}):
        count += message.get("r", {}).get("msg") == "SYSTEM READY"
    return count


async def test_a_flush_read_as_two_packets_is_one_open_with_one_banner(
    sim: SimController,
) -> None:
    # TCIOFLUSH sets FLUSHREAD, then FLUSHWRITE; a board that reads in between sees
    # two packets. The second is no new open, and brings no second banner.
    raw = RawHost(sim.data_path)
    try:
        assert raw.fd is not None
        await sim.wait_attached()
        termios.tcflush(raw.fd, termios.TCIFLUSH)
        await sim.wait_for(lambda: banners(sim) == 1)  # the flush was read: the banner
        termios.tcflush(raw.fd, termios.TCOFLUSH)
        assert await banners_before_answer(raw, sim) == 1
        assert banners(sim) == 1
    finally:
        raw.close()


async def test_a_fallback_banner_sent_after_the_flush_is_not_sent_again(
    sim: SimController,
) -> None:
    # The opener flushes, but the board has not read that flush when its fallback
    # timer runs: the timer takes the flush first, and the banner goes out once.
    sim.stop_reading()  # the flush waits in the pty, unread, while the timer runs
    raw = RawHost(sim.data_path)
    try:
        assert raw.fd is not None
        termios.tcflush(raw.fd, termios.TCIOFLUSH)
        await sim.wait_for(lambda: banners(sim) == 1)  # the fallback banner, after the flush
        sim.resume_reading()
        assert await banners_before_answer(raw, sim) == 1
        assert banners(sim) == 1
    finally:
        raw.close()


async def test_a_fallback_banner_the_flush_threw_away_is_sent_again(sim: SimController) -> None:
    raw = RawHost(sim.data_path)
    try:
        assert raw.fd is not None
        await sim.wait_for(lambda: banners(sim) == 1)  # an opener slow to flush
        termios.tcflush(raw.fd, termios.TCIOFLUSH)  # ...discards it
        assert await banners_before_answer(raw, sim) == 1
        assert banners(sim) == 2
    finally:
        raw.close()


async def raw_ask(raw: RawHost, line: bytes) -> dict[str, object]:
    """Write a line and read up to its `{r}` (status reports skipped)."""
    raw.write(line)
    while "r" not in (message := await raw.message()):
        pass
    return dict(message["r"])


async def test_flushing_again_in_an_open_is_no_new_open(sim: SimController) -> None:
    # Any host may flush whenever it likes (tty.setraw flushes, then a tcflush; a
    # reset of its input): a flush bit seen again is no reopen, and resets nothing.
    raw = RawHost(sim.data_path)
    try:
        assert raw.fd is not None
        termios.tcflush(raw.fd, termios.TCIOFLUSH)  # the opener's flush: the banner
        assert await banners_before_answer(raw, sim) == 1
        assert (await raw_ask(raw, b"{sv:0}\n"))["sv"] == 0
        for how in (termios.TCIFLUSH, termios.TCIFLUSH, termios.TCIOFLUSH):
            termios.tcflush(raw.fd, how)  # each read by the board before the next
            assert await banners_before_answer(raw, sim) == 0
        assert (await raw_ask(raw, b"{sv:n}\n"))["sv"] == 0  # an open would put back 1
        assert banners(sim) == 1
    finally:
        raw.close()


async def test_a_host_that_read_its_fallback_banner_and_wrote_gets_no_second_one(
    sim: SimController,
) -> None:
    # A non-flushing opener is done opening once it writes: a flush after that is
    # its own business, not a late opener's flush that threw the banner away.
    raw = RawHost(sim.data_path)
    try:
        assert raw.fd is not None
        assert (await raw.message())["r"]["msg"] == "SYSTEM READY"  # the fallback
        assert (await raw_ask(raw, b"{sv:n}\n"))["sv"] == 1
        termios.tcflush(raw.fd, termios.TCIFLUSH)
        assert await banners_before_answer(raw, sim) == 0
        assert banners(sim) == 1
    finally:
        raw.close()


async def test_a_reopen_the_board_could_not_see_is_still_a_new_open(sim: SimController) -> None:
    # Closed and opened again with no read in between (the board runs on this event
    # loop, so it cannot look while this code runs): no EIO, no hangup ever showed.
    # The board knows from the count of opens (inotify), and the new opener gets
    # the state of an open and a banner, whatever flush bits it sends.
    first = RawHost(sim.data_path)
    try:
        assert (await first.message())["r"]["msg"] == "SYSTEM READY"  # no flush: fallback
        assert (await raw_ask(first, b"{sv:0}\n"))["sv"] == 0
    finally:
        first.close()
    second = RawHost(sim.data_path)  # before the board could notice the close
    try:
        assert second.fd is not None
        termios.tcflush(second.fd, termios.TCIOFLUSH)
        assert await banners_before_answer(second, sim) == 1
        assert (await raw_ask(second, b"{sv:n}\n"))["sv"] == 1  # back to its default
    finally:
        second.close()


async def test_a_port_takes_what_was_written_when_the_board_asks_not_when_the_loop_gets_round(
    tmp_path: Path,
) -> None:
    """A board's receive interrupt takes bytes as they come; the board's loop asks its
    ports for what is waiting before it runs what is due (`read_waiting`), so a move
    that ends while the event loop is busy elsewhere never finds the planner empty with
    the host's next line already written (a host on time seen as late: an underflow)."""

    class Listener:
        def __init__(self) -> None:
            self.data = b""
            self.attached = asyncio.Event()

        def port_attached(self, port: PtyPort) -> None:
            self.attached.set()

        def port_detached(self, port: PtyPort) -> None:
            pass

        def port_data(self, port: PtyPort, data: bytes) -> None:
            self.data += data

        def port_flushed(self, port: PtyPort) -> None:
            pass

    listener = Listener()
    port = PtyPort("data", str(tmp_path / "tty"), listener)
    port.plug()
    host = os.open(port.path, os.O_RDWR | os.O_NOCTTY)
    try:
        async with asyncio.timeout(5):
            await listener.attached.wait()
        port.set_read_limit(0)  # the board's buffer full: nothing may be taken
        os.write(host, b"G1 X1\n")
        assert select.select([port._fd], [], [], 5)[0]  # at the master, not yet read
        port.read_waiting()
        assert listener.data == b""
        port.set_read_limit(64)  # room again; no loop iteration in between
        port.read_waiting()
        assert listener.data == b"G1 X1\n"
    finally:
        os.close(host)
        port.unplug()
