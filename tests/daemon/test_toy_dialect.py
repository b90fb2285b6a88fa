"""A third dialect from its own folder, with no edit anywhere in hostd (issue 28, part 5).

The toy (tests/toydialect/) is registered here, through the registry's
`register`, as a plug-in would; a daemon is configured with one toy machine
(`dialect = "toy"`, `data_port = "sim"`) and reached through the real Unix
socket; its board is the toy's own simulator on a real pty. It connects,
runs a job to completion, enters and leaves a lockout, and answers in its
own words.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import pytest
import pytest_asyncio

from hostd.config import ConfigError, parse_config
from hostd.protocol import dialects
from tests.daemon.conftest import Rpc, Running, running_daemon
from tests.daemon.test_api import fails, job_end
from tests.toydialect import TOY
from tests.toydialect.board import ToyBoard
from tests.toydialect.words import ALARMS, ERRORS

TOY_MACHINE = "sim1"


@pytest.fixture
def toy_registered() -> Iterator[None]:
    dialects.register(TOY)
    try:
        yield
    finally:
        dialects.unregister(TOY.name)


@pytest_asyncio.fixture
async def toy(tmp_path: Path, toy_registered: None) -> AsyncIterator[tuple[Running, Rpc]]:
    """A daemon of one toy machine, idle, and a client."""
    async with running_daemon(tmp_path, per_machine=[{"dialect": "toy", "greeting": 3}]) as d:
        client = await d.client()
        await d.idle(client, TOY_MACHINE)
        yield d, client
        await client.close()


def board(d: Running) -> ToyBoard:
    sim = d.daemon.sims[TOY_MACHINE]
    assert isinstance(sim, ToyBoard)  # the toy's own simulator, by its registry entry
    return sim


@pytest.mark.asyncio
async def test_a_toy_machine_connects_and_says_its_dialect(toy: tuple[Running, Rpc]) -> None:
    d, rpc = toy
    (entry,) = await rpc.call("machine.list")
    assert entry["id"] == TOY_MACHINE and entry["dialect"] == "toy"
    assert entry["state"]["name"] == "READY" and entry["supervisor"] == "idle"
    assert await rpc.call("machine.send", machine=TOY_MACHINE, line="G0 X4 Y2") == {
        "status": 0,
        "r": {},
    }
    assert board(d).position == {"X": 4.0, "Y": 2.0, "Z": 0.0}


@pytest.mark.asyncio
async def test_a_job_streams_to_completion_on_the_toy(toy: tuple[Running, Rpc]) -> None:
    d, rpc = toy
    program = "".join(f"G1 X{i % 7} Y{i % 3} F600\n" for i in range(30))
    await rpc.call("file.upload", name="toy.gcode", data=program)
    await rpc.call("subscribe", topics=["job"], machine=TOY_MACHINE)
    started = await rpc.call("job.start", machine=TOY_MACHINE, file="toy.gcode")
    job = await job_end(rpc, started["job"])
    assert job["state"] == "completed"
    assert job["lines_total"] == job["lines_sent"] == job["lines_acked"] == 30
    # Every line reached the board once, in order, with its file line as N word.
    lines = [r for r in board(d).received if r.startswith(b"N")]
    assert lines == [f"N{i + 1} G1 X{i % 7} Y{i % 3} F600".encode() for i in range(30)]
    assert board(d).position == {"X": float(29 % 7), "Y": float(29 % 3), "Z": 0.0}


@pytest.mark.asyncio
async def test_the_toy_enters_and_leaves_a_lockout(toy: tuple[Running, Rpc]) -> None:
    d, rpc = toy
    await rpc.call("subscribe", topics=["exception", "status"], machine=TOY_MACHINE)
    assert await rpc.call("machine.alarm", machine=TOY_MACHINE) == {}  # the toy's `ALARM`
    exception = await rpc.notification(lambda n: n["method"] == "exception")
    assert exception["params"]["report"] == {"alarm": 1, "msg": ALARMS[1]}
    await rpc.notification(
        lambda n: n["method"] == "status" and n["params"]["snapshot"]["state"]["name"] == "ALARM"
    )
    # Actions are refused on the host, in hostd's words for a lockout; nothing reaches it.
    before = len(board(d).received)
    err = await fails(204, rpc.call("machine.send", machine=TOY_MACHINE, line="G0 X1"))
    assert ALARMS[1] in err.message
    assert len(board(d).received) == before
    locked = (await rpc.call("machine.status", machine=TOY_MACHINE))["lockout"]
    assert locked == {"state": "ALARM", "message": ALARMS[1], "clear": "machine.clear"}
    assert await rpc.call("machine.clear", machine=TOY_MACHINE) == {}  # the toy's `UNLOCK`
    snap = await rpc.call("machine.status", machine=TOY_MACHINE)
    assert snap["state"]["name"] == "READY" and snap["lockout"] is None
    assert board(d).received[-1] == b"UNLOCK"
    assert (await rpc.call("machine.send", machine=TOY_MACHINE, line="G0 X1"))["status"] == 0


@pytest.mark.asyncio
async def test_a_job_fails_when_the_toy_trips_its_own_alarm(toy: tuple[Running, Rpc]) -> None:
    d, rpc = toy
    await rpc.call("subscribe", topics=["job", "status"], machine=TOY_MACHINE)
    board(d).alarm(2)  # a limit switch, on the board's side
    await rpc.notification(
        lambda n: n["method"] == "status" and n["params"]["snapshot"]["state"]["name"] == "ALARM"
    )
    locked = (await rpc.call("machine.status", machine=TOY_MACHINE))["lockout"]
    assert locked["message"] == ALARMS[2]
    await rpc.call("file.upload", name="toy.gcode", data="G1 X1\n")
    await fails(204, rpc.call("job.start", machine=TOY_MACHINE, file="toy.gcode"))
    await rpc.call("machine.clear", machine=TOY_MACHINE)
    started = await rpc.call("job.start", machine=TOY_MACHINE, file="toy.gcode")
    assert (await job_end(rpc, started["job"]))["state"] == "completed"


@pytest.mark.asyncio
@pytest.mark.parametrize(("line", "code"), [("G0 Q5", 1), ("G0 X", 2), ("G0" + " X1" * 30, 3)])
async def test_a_refused_line_comes_back_in_the_toys_words(
    toy: tuple[Running, Rpc], line: str, code: int
) -> None:
    _, rpc = toy
    if code == 3:
        # Too long for the toy: refused on the host by the toy's own encoder.
        err = await fails(-32602, rpc.call("machine.send", machine=TOY_MACHINE, line=line))
        assert "longer than the toy takes" in err.message
        return
    err = await fails(1005, rpc.call("machine.send", machine=TOY_MACHINE, line=line))
    assert err.data == {"status": code, "msg": ERRORS[code]}
    assert f"controller answered {code}: {ERRORS[code]}" in err.message


@pytest.mark.asyncio
async def test_a_job_line_the_toy_refuses_fails_the_job_in_its_words(
    toy: tuple[Running, Rpc],
) -> None:
    _, rpc = toy
    await rpc.call("file.upload", name="bad.gcode", data="G1 X1\nG1 X2 Q5\nG1 X3\n")
    await rpc.call("subscribe", topics=["job"], machine=TOY_MACHINE)
    started = await rpc.call("job.start", machine=TOY_MACHINE, file="bad.gcode")
    job = await job_end(rpc, started["job"])
    assert job["state"] == "failed"
    assert job["error"]["code"] == 1005 and ERRORS[1] in job["error"]["message"]
    assert "line 2" in job["error"]["message"]


def test_the_toys_keys_are_config_keys_only_for_a_toy_machine(toy_registered: None) -> None:
    """Its schema addition (`greeting`) is validated as any key; another dialect's is not."""
    machine = {"id": "t", "data_port": "sim", "dialect": "toy"}
    config = parse_config({"machines": [machine | {"greeting": 2}]})
    assert config.machines[0].spec is TOY
    with pytest.raises(ConfigError, match=r"machines\[0\]\.greeting"):
        parse_config({"machines": [machine | {"greeting": 0}]})
    with pytest.raises(ConfigError, match=r"machines\[0\]\.window .*unknown key"):
        parse_config({"machines": [machine | {"window": 4}]})
    with pytest.raises(ConfigError, match="one port"):
        parse_config({"machines": [machine | {"control_port": "/dev/x"}]})


def test_without_registration_the_toy_is_an_unknown_dialect() -> None:
    with pytest.raises(ConfigError, match="unknown dialect 'toy'"):
        parse_config({"machines": [{"id": "t", "data_port": "sim", "dialect": "toy"}]})
