"""The realtime fast path end to end: a real Unix socket, a daemon, a simulated board on a pty.

A feedhold in the shape clients send (`fastpath.Shape`) is read without the
JSON parser; these say that a user sees no difference: the same answers as
the general way, and the job's `!` reaching the board with no job line
written after it until the cycle start.
"""

from __future__ import annotations

import asyncio
import json
from typing import Any

import pytest

from tests.daemon.conftest import Rpc, Running

pytestmark = pytest.mark.asyncio


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


def _is_job_line(data: bytes) -> bool:
    return b"G1" in data


async def test_a_feedhold_pauses_the_streaming_job_and_no_job_line_follows_its_bang(
    hostd: Running, rpc: Rpc
) -> None:
    # Moves long enough that the job is still streaming when the hold comes, on a loaded
    # test machine too.
    program = "".join(f"G1 X{(i % 2) * 40} F3000\n" for i in range(300))
    await rpc.call("file.upload", name="long.gcode", data=program)
    await rpc.call("subscribe", topics=["job"], machine="sim1")
    started = await rpc.call("job.start", machine="sim1", file="long.gcode")
    await rpc.notification(
        lambda n: n["method"] == "job" and n["params"]["job"]["lines_acked"] >= 3
    )
    sim = hostd.daemon.sims["sim1"]
    seen = len(sim.received)
    raw = await Raw.open(hostd.socket)
    try:
        # bench/client.py's bytes: compact, the id before the method
        hold = b'{"jsonrpc":"2.0","id":7,"method":"machine.feedhold","params":{"machine":"sim1"}}\n'
        assert await raw.ask(hold) == {"jsonrpc": "2.0", "result": {}, "id": 7}
        assert (await rpc.call("job.get", job=started["job"]))["state"] == "paused"
        await sim.wait_received(lambda: any(r.data == b"!" for r in list(sim.received)[seen:]))
        # The CLI's bytes: json.dumps' separators, the method before the id, a string id.
        resume = (
            b'{"jsonrpc": "2.0", "method": "machine.cycle_start", "id": "go", '
            b'"params": {"machine": "sim1"}}\n'
        )
        assert await raw.ask(resume) == {"jsonrpc": "2.0", "result": {}, "id": "go"}
        assert (await rpc.call("job.get", job=started["job"]))["state"] == "running"

        def streams_again() -> bool:
            after = list(sim.received)[seen:]
            kinds = [(r.kind, r.data) for r in after]
            if ("realtime", b"~") not in kinds:
                return False
            return any(_is_job_line(r.data) for r in after[kinds.index(("realtime", b"~")) :])

        await sim.wait_received(streams_again)
    finally:
        await raw.close()
    after = list(sim.received)[seen:]
    bang = next(i for i, r in enumerate(after) if r.kind == "realtime" and r.data == b"!")
    tilde = next(i for i, r in enumerate(after) if r.kind == "realtime" and r.data == b"~")
    assert bang < tilde
    assert not [r.data for r in after[bang:tilde] if _is_job_line(r.data)]
    await rpc.call("job.cancel", machine="sim1")


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
