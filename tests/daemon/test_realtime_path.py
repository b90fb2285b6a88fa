"""The realtime fast path end to end: a real Unix socket, a daemon, a simulated board on a pty.

A feedhold in the shape clients send (`fastpath.Shape`) is read without the
JSON parser; these say that a user sees no difference: the same answers as
the general way, and the job's `!` reaching the board with no job line
written after it until the cycle start.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable
from typing import Any

import pytest

from hostd.sim.config import Received
from tests.daemon.conftest import GRBL, Rpc, Running

pytestmark = pytest.mark.asyncio

REALTIME = b"!~?"  # the realtime bytes these tests write, and the polls' `?`
WAIT = 30.0  # a bound for a wait that would otherwise hang (six test workers, two cores)


class Raw:
    """A client that writes request lines byte for byte and reads each answer line."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer

    @classmethod
    async def open(cls, path: str) -> Raw:
        return cls(*await asyncio.open_unix_connection(path))

    async def ask(self, line: bytes) -> dict[str, Any]:
        self.writer.write(line)
        async with asyncio.timeout(15):  # a bound for a test that would hang, not a timing
            answer: dict[str, Any] = json.loads(await self.reader.readline())
        return answer

    async def close(self) -> None:
        self.writer.close()
        await self.writer.wait_closed()


def _taken(received: list[Received]) -> bytes:
    """The bytes the board took, in the order it took them.

    A simulated g2core records each line (without its newline) and each realtime byte
    apart; a grbl board records each read whole (kind "raw"), and one read holds what
    the host wrote since the last: when the event loop runs late (a loaded machine),
    the `!` shares its read with the job line written just before it, or with the `?`
    written 20 ms after it (`SETTLE_POLL`). So the order is judged byte by byte, not
    read by read.
    """
    return b"".join(r.data + b"\n" if r.kind == "line" else r.data for r in received)


def _job_lines_from(taken: bytes, start: int, end: int | None = None) -> list[bytes]:
    """The job lines whose first byte the board took at `start` or later (before `end`).

    Realtime bytes taken before a line's first byte are not part of it; a line begun
    before a realtime byte and ended after it (the byte reached the board ahead of the
    rest of the line) was written before it: it does not count.
    """
    found, at = [], 0
    for line in taken.split(b"\n"):
        first = at + len(line) - len(line.lstrip(REALTIME))
        if start <= first and (end is None or first < end) and b"G1" in line:
            found.append(line)
        at += len(line) + 1
    return found


async def test_a_feedhold_pauses_the_streaming_job_and_no_job_line_follows_its_bang(
    hostd: Running, rpc: Rpc
) -> None:
    await _hold_and_resume(hostd, rpc, "sim1", held=None)


async def test_the_same_on_a_grbl_board(both: tuple[Running, Rpc]) -> None:
    # grbl drops a cycle start that comes while its hold still decelerates (gnea/grbl
    # grbl/protocol.c:348, "Cycle start only when IDLE or when a hold is complete"), so the
    # resume here waits for the board's Hold:0, as an operator would.
    hostd, rpc = both
    sim = hostd.daemon.sims[GRBL]
    await _hold_and_resume(hostd, rpc, GRBL, held=lambda: sim.state == "Hold:0")


async def _hold_and_resume(
    hostd: Running, rpc: Rpc, machine: str, held: Callable[[], bool] | None
) -> None:
    """A job streams; a feedhold in bench's bytes, a cycle start in the CLI's, on one socket."""
    # Moves long enough that the job is still streaming when the hold comes, on a loaded
    # test machine too.
    program = "".join(f"G1 X{(i % 2) * 40} F3000\n" for i in range(300))
    await rpc.call("file.upload", name="long.gcode", data=program)
    await rpc.call("subscribe", topics=["job"], machine=machine)
    started = await rpc.call("job.start", machine=machine, file="long.gcode")
    await rpc.notification(
        lambda n: (
            n["method"] == "job"
            and n["params"]["job"]["id"] == started["job"]
            and n["params"]["job"]["lines_acked"] >= 3
        )
    )
    sim = hostd.daemon.sims[machine]
    seen = len(sim.received)
    named = machine.encode()
    raw = await Raw.open(hostd.socket)
    try:
        # bench/client.py's bytes: compact, the id before the method
        hold = (
            b'{"jsonrpc":"2.0","id":7,"method":"machine.feedhold","params":{"machine":"'
            + named
            + b'"}}\n'
        )
        assert await raw.ask(hold) == {"jsonrpc": "2.0", "result": {}, "id": 7}
        assert (await rpc.call("job.get", job=started["job"]))["state"] == "paused"
        await sim.wait_for(lambda: b"!" in _taken(list(sim.received)[seen:]), WAIT)
        if held is not None:
            await sim.wait_for(held, WAIT)
        # The CLI's bytes: json.dumps' separators, the method before the id, a string id.
        resume = (
            b'{"jsonrpc": "2.0", "method": "machine.cycle_start", "id": "go", '
            b'"params": {"machine": "' + named + b'"}}\n'
        )
        assert await raw.ask(resume) == {"jsonrpc": "2.0", "result": {}, "id": "go"}
        assert (await rpc.call("job.get", job=started["job"]))["state"] == "running"

        def streams_again() -> bool:
            taken = _taken(list(sim.received)[seen:])
            tilde = taken.find(b"~")
            return tilde >= 0 and bool(_job_lines_from(taken, tilde))

        await sim.wait_for(streams_again, WAIT)
    finally:
        await raw.close()
    taken = _taken(list(sim.received)[seen:])
    bang, tilde = taken.find(b"!"), taken.find(b"~")
    assert 0 <= bang < tilde, taken
    assert not _job_lines_from(taken, bang, tilde), taken
    await rpc.call("job.cancel", machine=machine)


async def test_the_fast_shape_and_the_general_way_answer_alike(hostd: Running, rpc: Rpc) -> None:
    raw = await Raw.open(hostd.socket)
    try:
        for machine, escaped in (("sim1", "sim\\u0031"), ("nope", "n\\u006fpe")):
            fast = await raw.ask(
                b'{"jsonrpc":"2.0","id":1,"method":"machine.feedhold","params":{"machine":"'
                + machine.encode()
                + b'"}}\n'
            )
            # An escape in a string is not the fast shape: the JSON parser reads this one.
            general = await raw.ask(
                b'{"jsonrpc":"2.0","id":1,"method":"machine.feedhold","params":{"machine":"'
                + escaped.encode()
                + b'"}}\n'
            )
            assert fast == general
        assert fast["error"]["code"] == 1001  # the unknown machine, with the request's id
        assert fast["id"] == 1
        back = (
            b'{"jsonrpc":"2.0","id":2,"method":"machine.cycle_start","params":{"machine":"sim1"}}\n'
        )
        assert await raw.ask(back) == {"jsonrpc": "2.0", "result": {}, "id": 2}
    finally:
        await raw.close()
