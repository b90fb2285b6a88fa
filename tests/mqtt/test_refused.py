"""The request ids of refused commands, kept so that a copy never runs: bounded in a flood.

A command refused for a passing reason (over the rate, too many running) is told to try
again later; a copy of it delivered later (its PUBACK lost: test_session.py) must not run,
so its request_id is kept. Nothing bounds refusals but this store (the rate limit itself
refuses a flood): here a flood of them, taken as the bridge takes what the broker
delivers (`Commands.take`), leaves at most MAX_REFUSED ids, the newest, each for as long
as a copy could pass the age check.
"""

from __future__ import annotations

import asyncio
import itertools
import json
from typing import Any

import aiomqtt
import pytest
import structlog
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from hostd.api import rpc
from hostd.api.mqtt.bridge import MAX_INCOMING
from hostd.api.mqtt.commands import MAX_REFUSED, Commands, RecentIds
from hostd.api.mqtt.config import MqttConfig
from hostd.api.mqtt.outbox import Outbox, Outgoing

TOPIC = "test/h1/sim1/cmd/daemon.info"
REPLIES = "test/h1/replies/flood"
MIDS = itertools.count(1)


class Bench:
    """A bridge's receive side, without a broker: its clocks held by the test."""

    def __init__(self, tasks: asyncio.TaskGroup, burst: int = 1) -> None:
        self.now = 1_000.0  # the rate's clock and the wall clock, both moved by the test
        self.runs: list[str] = []
        self.tasks = tasks
        self.gate = asyncio.Event()  # a command runs until it is set
        self.gate.set()

        async def info() -> dict[str, Any]:
            self.runs.append("info")
            await self.gate.wait()
            return {}

        config = MqttConfig.model_validate(
            {
                "url": "mqtt://127.0.0.1:1883",
                "topic_prefix": "test/h1",
                "commands": True,
                "allow": ["daemon.info"],
                "command_rate": 1,
                "command_burst": burst,
                "command_max_age": 30,
            }
        )
        self.outbox = Outbox(max_events=100)
        methods = {"daemon.info": rpc.Method(info, None)}
        # Each refusal is logged; not printed here, where ten thousand are the point.
        log = structlog.wrap_logger(structlog.ReturnLogger(), processors=[])
        self.commands = Commands(
            config, methods, self.outbox, log, lambda: self.now, lambda: self.now
        )

    def send(self, request_id: str, ahead: float = 0.0) -> None:
        """A command as the broker delivers it, sent `ahead` s ahead of our clock."""
        properties = Properties(PacketTypes.PUBLISH)  # type: ignore[no-untyped-call]
        properties.ResponseTopic = REPLIES
        properties.CorrelationData = request_id.encode()
        properties.UserProperty = [
            ("request_id", request_id),
            ("sent_at", f"{self.now + ahead:.3f}"),
        ]
        message = aiomqtt.Message(TOPIC, b"{}", 1, False, next(MIDS), properties)
        self.commands.take(message, self.tasks)

    async def answer(self, request_id: str) -> Any:
        """The last answer to `request_id` in the outbox, once what runs has run."""
        await asyncio.sleep(0)  # a started command's task runs and answers
        while self.commands.running:
            await asyncio.wait(self.commands.running)
        found = None
        while isinstance(item := self.outbox.take(self.now), Outgoing):
            self.outbox.published(item, self.now)
            if item.correlation == request_id.encode():
                found = json.loads(item.payload)
        return found


@pytest.mark.asyncio
async def test_a_flood_of_refused_commands_keeps_at_most_the_newest_ids() -> None:
    async with asyncio.TaskGroup() as tasks:
        bench = Bench(tasks)
        bench.send("ran")  # the burst of 1
        flood = [f"f{i}" for i in range(MAX_REFUSED + 500)]
        for request_id in flood:  # the clock held: every one over the rate
            bench.send(request_id)
        assert bench.commands.kept_refused == MAX_REFUSED
        assert (await bench.answer(flood[-1]))["error"]["code"] == -32001
        bench.now += 1.0  # one more may pass: the newest refused, again
        bench.send(flood[-1])
        again = await bench.answer(flood[-1])
        assert again["error"] == {"code": -32002, "message": f"command {flood[-1]} already refused"}
        bench.now += 1.0  # the oldest refused, forgotten at the bound, runs if it comes again
        bench.send(flood[0])
        assert "result" in await bench.answer(flood[0])
        assert bench.runs == ["info", "info"]
        bench.now += 31.0  # past sent_at + command_max_age: a copy is too old to run anyway
        bench.send("late")
        assert "result" in await bench.answer("late")
        assert bench.commands.kept_refused == 0


@pytest.mark.asyncio
async def test_a_command_refused_with_too_many_running_never_runs_when_it_comes_again() -> None:
    async with asyncio.TaskGroup() as tasks:
        bench = Bench(tasks, burst=100)
        bench.gate.clear()
        for i in range(16):
            bench.send(f"r{i}")
        bench.send("full")
        bench.gate.set()
        full = await bench.answer("full")
        assert full["error"]["code"] == -32000 and "16 commands running" in full["error"]["message"]
        bench.send("full")  # delivered again, none running now
        again = await bench.answer("full")
        assert again["error"] == {"code": -32002, "message": "command full already refused"}
        assert len(bench.runs) == 16


@pytest.mark.asyncio
async def test_a_command_from_the_future_never_runs_when_a_copy_comes_once_it_would_pass() -> None:
    async with asyncio.TaskGroup() as tasks:
        bench = Bench(tasks, burst=10)
        bench.send("ahead", ahead=40.0)  # over command_max_age (30 s) in the future
        ahead = await bench.answer("ahead")
        assert ahead["error"]["code"] == -32002 and "in the future" in ahead["error"]["message"]
        bench.now += 20.0  # a copy now would be 20 s ahead: within the 30 s
        bench.send("ahead", ahead=20.0)
        again = await bench.answer("ahead")
        assert again["error"] == {"code": -32002, "message": "command ahead already refused"}
        assert bench.runs == []


def test_the_bound_holds_every_command_in_flight_to_the_bridge() -> None:
    """A refused command comes again after no more than Receive Maximum other commands
    (what the broker had in flight to us when its PUBACK was lost): it is still kept."""
    assert MAX_REFUSED >= MAX_INCOMING


def test_recent_ids_expire_in_any_order_and_forget_the_oldest_added_at_the_bound() -> None:
    ids = RecentIds(bound=3)
    ids.add("a", 10.0)
    ids.add("b", 5.0)
    ids.add("c", 20.0)
    assert ids.holds("b", 5.0) and not ids.holds("b", 6.0)  # expired behind a later one
    ids.add("a", 8.0)  # again: the newest now, kept as long as it was
    ids.add("d", 30.0)  # over the bound: the oldest added (b) goes, not a
    assert len(ids) == 3 and ids.holds("a", 10.0) and ids.holds("d", 10.0)
    ids.add("e", 30.0)  # c goes
    assert not ids.holds("c", 10.0) and ids.holds("e", 10.0)
    assert ids.holds("a", 10.0) and not ids.holds("a", 11.0)
    unbounded = RecentIds()
    for i in range(100_000):
        unbounded.add(str(i), float(i))
    assert len(unbounded) == 100_000
    assert not unbounded.holds("0", 99_999.0) and len(unbounded) == 1
