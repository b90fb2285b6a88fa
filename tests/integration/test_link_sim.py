"""The link and the codec against the simulated board, over real pseudo-terminals."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
import pytest_asyncio

from hostd.link import Channel, LineReceived, Link, LinkLost
from hostd.protocol.commands import Realtime, encode_get, encode_line, encode_realtime
from hostd.protocol.linemode import InFlight, LineModeSender
from hostd.protocol.messages import Banner, Message, Response, StatusReport, Unparseable
from hostd.protocol.parser import parse_line
from hostd.protocol.states import MachineState
from hostd.sim import SimConfig, SimController

pytestmark = pytest.mark.asyncio

FAST = SimConfig(instant=True, status_interval=0.02, feedhold_decel=0.01, boot_time=0.01)


@pytest_asyncio.fixture
async def sim(tmp_path: Path) -> AsyncIterator[SimController]:
    async with SimController(str(tmp_path / "ttyG2"), config=FAST) as sim:
        yield sim


@pytest_asyncio.fixture
async def dual_sim(tmp_path: Path) -> AsyncIterator[SimController]:
    async with SimController(
        str(tmp_path / "ttyG2-data"), control_path=str(tmp_path / "ttyG2-ctrl"), config=FAST
    ) as sim:
        yield sim


async def messages(link: Link, until: type) -> list[tuple[Channel, Message]]:
    """Everything read up to and including the first message of type `until`."""
    got: list[tuple[Channel, Message]] = []
    async with asyncio.timeout(2):
        while True:
            for event in await link.read():
                assert isinstance(event, LineReceived), event
                msg = parse_line(event.line)
                got.append((event.channel, msg))
                if isinstance(msg, until):
                    return got


async def test_banner_on_open(sim: SimController) -> None:
    link = await Link.open(sim.data_path)
    try:
        (*_, (_, banner)) = await messages(link, Banner)
        assert isinstance(banner, Banner)
        assert banner.fb is not None and banner.fb < 200
    finally:
        await link.close()


async def test_line_mode_exchange_answers_every_line_in_order(sim: SimController) -> None:
    link = await Link.open(sim.data_path)
    try:
        await messages(link, Banner)
        sender = LineModeSender(window=4)
        program = [f"G1 X{i} Y{i} F3000" for i in range(1, 21)]
        answered: list[int] = []
        queue = list(enumerate(program, start=1))
        async with asyncio.timeout(5):
            while len(answered) < len(program):
                while queue and sender.has_room:
                    number, text = queue.pop(0)
                    line = encode_line(text)
                    assert link.write_line(line)
                    sender.sent(InFlight(line, file_line=number))
                for event in await link.read():
                    assert isinstance(event, LineReceived)
                    msg = parse_line(event.line)
                    if isinstance(msg, Response):
                        assert msg.ok
                        entry = sender.answered(msg)[0]
                        assert entry.file_line is not None
                        answered.append(entry.file_line)
        assert answered == list(range(1, 21))
        lines = [r.data for r in sim.received if r.kind == "line"]
        assert lines == [p.encode() for p in program]
    finally:
        await link.close()


async def test_dual_port_all_output_arrives_on_the_control_port(
    dual_sim: SimController,
) -> None:
    assert dual_sim.control_path is not None
    link = await Link.open(dual_sim.data_path, dual_sim.control_path)
    try:
        got = await messages(link, Banner)
        link.write_line(encode_line("G1 X5 F3000"))
        got += await messages(link, Response)
        link.write_control(encode_get("xvm"))
        got += await messages(link, Response)
        assert {channel for channel, _ in got} == {Channel.CONTROL}
        ports = {(r.port, r.data) for r in dual_sim.received}
        assert ("data", b"G1 X5 F3000") in ports
        assert ("control", b'{"xvm":null}') in ports
    finally:
        await link.close()


async def test_realtime_feedhold_reaches_the_board_between_lines(sim: SimController) -> None:
    link = await Link.open(sim.data_path)
    try:
        await messages(link, Banner)
        link.write_line(encode_line("G1 X10 F3000"))
        link.write_control(encode_realtime(Realtime.FEEDHOLD))
        await sim.wait_received(lambda: any(r.kind == "realtime" for r in sim.received))
        kinds = [(r.kind, r.data) for r in sim.received]
        assert kinds == [("line", b"G1 X10 F3000"), ("realtime", b"!")]
    finally:
        await link.close()


async def test_unplug_is_seen_as_a_typed_event_within_a_second(sim: SimController) -> None:
    link = await Link.open(sim.data_path)
    try:
        await messages(link, Banner)
        await sim.unplug()
        async with asyncio.timeout(1):
            events = await link.read()
            while not any(isinstance(e, LinkLost) for e in events):
                events = await link.read()
        assert link.lost is not None
        assert not await asyncio.to_thread(Path(sim.data_path).exists)
    finally:
        await link.close()


async def test_replug_at_the_same_path_brings_a_new_banner(sim: SimController) -> None:
    link = await Link.open(sim.data_path)
    await messages(link, Banner)
    await sim.unplug()
    async with asyncio.timeout(1):
        while link.lost is None:
            await link.read()
    await link.close()
    await sim.replug()
    link = await Link.open(sim.data_path)
    try:
        await messages(link, Banner)
    finally:
        await link.close()


async def test_garbage_from_the_board_is_unparseable_and_the_reader_goes_on(
    sim: SimController,
) -> None:
    link = await Link.open(sim.data_path)
    try:
        await messages(link, Banner)
        sim.inject_garbage(b'\xff\xfe\x00{"r":{"x"\n{{{{\n')
        link.write_line(encode_get("sr"))
        got = [msg for _, msg in await messages(link, Response)]
        bad = [m for m in got if isinstance(m, Unparseable)]
        assert len(bad) == 2
        assert bad[0].raw.startswith(b"\xff\xfe\x00")
        response = got[-1]
        assert isinstance(response, Response) and response.status_report is not None
    finally:
        await link.close()


async def test_status_reports_follow_a_move(sim: SimController) -> None:
    link = await Link.open(sim.data_path)
    try:
        await messages(link, Banner)
        link.write_line(encode_line("G1 X7 F3000"))
        states: list[int] = []
        async with asyncio.timeout(2):
            while MachineState.PROGRAM_STOP not in states:
                for event in await link.read():
                    assert isinstance(event, LineReceived)
                    msg = parse_line(event.line)
                    if isinstance(msg, StatusReport) and "stat" in msg.fields:
                        states.append(msg.fields["stat"])
        assert sim.position["x"] == pytest.approx(7.0)
    finally:
        await link.close()
