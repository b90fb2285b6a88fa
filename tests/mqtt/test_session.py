"""Commands across a dropped connection, over a real mosquitto that runs on throughout.

The broker keeps the bridge's session (`command_max_age`) and sends again, on the next
connection, every command it has not seen acknowledged; the bridge acknowledges a
command only once it has taken it. So a command sent while the bridge is away, or read
by it but not yet taken when the connection drops, is run on the next connection, once;
one grown stale on the way is refused out loud, and one delivered again is not run again.
A `Cable` (conftest.py) between the bridge and the broker is what drops the connection.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiomqtt
import pytest
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from hostd.api.mqtt import topics
from tests.mqtt.conftest import WAIT, Bridged, Broker, Cable, Watcher, bridged, cable, decoded
from tests.mqtt.conftest import watching as watching_broker

pytestmark = pytest.mark.asyncio

SETTINGS: dict[str, Any] = {
    "commands": True,
    "allow": ["daemon.info"],
    "command_rate": 1000,
    "command_burst": 1000,
    "max_events": 1000,
}
COMMAND = "test/h1/sim1/cmd/daemon.info"
SEND = "test/h1/sim1/cmd/machine.send"
REPLIES = "test/h1/replies/away"


async def away(b: Bridged, hop: Cable, caller: Watcher) -> None:
    """Pull the cable: the bridge is disconnected and the broker has seen it go (its will)."""
    await hop.unplug()
    async with asyncio.timeout(WAIT):
        await b.bridge.disconnected.wait()
    await caller.state("test/h1/online", lambda payload: payload == "offline")


@contextlib.asynccontextmanager
async def bridge_away(
    tmp_path: Path, broker: Broker, **mqtt: Any
) -> AsyncIterator[tuple[Cable, Bridged, Watcher]]:
    """A bridge behind a cable, seen online, then away; a caller listening for replies.
    `mqtt`: settings over SETTINGS."""
    async with (
        cable(broker) as hop,
        bridged(tmp_path, broker, url=hop.url, **{**SETTINGS, **mqtt}) as b,
        watching_broker(broker, "test/h1/online") as caller,
    ):
        await caller.state("test/h1/online", lambda payload: payload == "online")
        await caller.client.subscribe(REPLIES, qos=1)
        await away(b, hop, caller)
        yield hop, b, caller


async def every_reply(caller: Watcher) -> list[tuple[bytes, Any]]:
    """Every reply on REPLIES, in order, up to that of a last command sent now: what was
    delivered again was delivered before it (one session, in order), so nothing more of
    it comes after."""
    await caller.send(COMMAND, {}, b"last", reply_to=REPLIES)
    found: list[tuple[bytes, Any]] = []
    while not found or found[-1][0] != b"last":
        message = await caller.next(lambda m: str(m.topic) == REPLIES)
        found.append((getattr(message.properties, "CorrelationData", b""), decoded(message)))
    return found


def runs(replies: list[tuple[bytes, Any]]) -> dict[bytes, set[int]]:
    """The runs of each command, by correlation data: a run answers with a result and an
    `id` of its own (a reply published again after a drop, its PUBACK lost, has the same)."""
    found: dict[bytes, set[int]] = {}
    for correlation, answer in replies:
        if "result" in answer and correlation != b"last":
            found.setdefault(correlation, set()).add(answer["id"])
    return found


def once(replies: list[tuple[bytes, Any]], commands: list[bytes]) -> bool:
    """Whether each of `commands`, and no other, ran exactly once."""
    ran = runs(replies)
    return sorted(ran) == sorted(commands) and all(len(ids) == 1 for ids in ran.values())


def rate_limited(answer: Any) -> bool:
    return bool(answer.get("error", {}).get("code") == -32001)


def already_refused(answer: Any) -> bool:
    error = answer.get("error", {})
    return bool(error.get("code") == -32002 and "already refused" in error.get("message", ""))


def already_run(answer: Any) -> bool:
    error = answer.get("error", {})
    return bool(error.get("code") == -32002 and "already run" in error.get("message", ""))


async def test_commands_sent_while_the_bridge_is_away_run_once_when_it_is_back(
    tmp_path: Path, broker: Broker
) -> None:
    async with bridge_away(tmp_path, broker) as (hop, b, caller):
        # Published while the bridge is away (each one's PUBACK from the broker awaited):
        # the broker holds them in the bridge's session.
        sent = [f"c{i}".encode() for i in range(10)]
        for correlation in sent:
            await caller.send(COMMAND, {}, correlation, reply_to=REPLIES)
        await caller.send(COMMAND, {}, b"stale", reply_to=REPLIES, sent_at=time.time() - 120)
        await caller.send(COMMAND, {}, b"first", reply_to=REPLIES, request_id="twice")
        await caller.send(COMMAND, {}, b"again", reply_to=REPLIES, request_id="twice")
        await hop.plug()
        replies = await every_reply(caller)
        assert b.bridge.connections == 2
    assert once(replies, [*sent, b"first"]), replies
    answers = dict(replies)
    stale = answers[b"stale"]["error"]
    assert stale["code"] == -32002 and "s ago, over 30 s" in stale["message"], stale
    assert already_run(answers[b"again"]), answers[b"again"]


async def test_commands_read_but_not_taken_when_the_connection_drops_come_again(
    tmp_path: Path, broker: Broker
) -> None:
    """The connection drops just after the broker has had a few PUBACKs, with the other
    commands read by the bridge's client (mosquitto sends 20 unacknowledged at once) but
    not yet taken: those come again on the next connection. paho used to acknowledge each
    as it read it, ahead of the bridge taking it: those were lost with the client."""
    async with bridge_away(tmp_path, broker) as (hop, b, caller):
        sent = [f"c{i}".encode() for i in range(30)]
        for correlation in sent:
            await caller.send(COMMAND, {}, correlation, reply_to=REPLIES)
        hop.cut_after_pubacks = hop.pubacks + 3
        await hop.plug()  # the session's commands come at once; 3 PUBACKs, then the cut
        async with asyncio.timeout(WAIT):
            await hop.cut.wait()
            await b.bridge.disconnected.wait()
        # (No wait for the will here: it would pass over, and lose, the replies before it.)
        assert b.bridge.connections == 2  # a command is acknowledged once subscribed
        await hop.plug()
        replies = await every_reply(caller)
        assert b.bridge.connections == 3
    assert once(replies, sent), replies  # none lost, none run twice
    # Taken but its PUBACK lost in the cut: delivered again, refused, answered.
    again = [answer for c, answer in replies if "result" not in answer]
    assert all(already_run(answer) for answer in again), again


async def test_a_command_refused_for_the_rate_never_runs_when_it_comes_again(
    tmp_path: Path, broker: Broker
) -> None:
    """A command refused over the rate ("try again later") whose PUBACK is lost in a cut
    comes again on the next connection, when the rate would let it pass: it is refused as
    already refused, and the board gets its line once, from the caller's new try. It used
    to run then: the machine moved twice."""
    skipped = [0.0]  # moves the bridge's clock on, and so refills its command rate
    settings = {"allow": ["daemon.info", "machine.send"], "command_rate": 0.001}
    async with bridge_away(
        tmp_path,
        broker,
        clock=lambda: time.monotonic() + skipped[0],
        command_burst=2,
        **settings,
    ) as (hop, b, caller):
        client = await b.running.client()
        await b.running.idle(client)
        await client.close()
        move = {"line": "G0 X1.25"}
        for correlation in (b"first", b"second"):  # the 2 commands of the burst
            await caller.send(COMMAND, {}, correlation, reply_to=REPLIES)
        await caller.send(SEND, move, b"limited", reply_to=REPLIES, request_id="limited")
        hop.lose_puback = hop.pubacks + 3  # that of `limited`, refused over the rate
        await hop.plug()
        async with asyncio.timeout(WAIT):
            await hop.cut.wait()
            await b.bridge.disconnected.wait()
        skipped[0] += 10_000.0  # the rate would let 2 more pass: `limited` again, `again`
        # The caller, told to try again later, does: the same move under a new request_id.
        await caller.send(SEND, move, b"again", reply_to=REPLIES, request_id="again")
        await hop.plug()
        answers: dict[bytes, list[Any]] = {b"limited": [], b"again": []}
        while not (
            any(rate_limited(answer) for answer in answers[b"limited"])
            and any(not rate_limited(answer) for answer in answers[b"limited"])
            and answers[b"again"]
        ):
            message = await caller.next(lambda m: str(m.topic) == REPLIES)
            correlation = getattr(message.properties, "CorrelationData", b"")
            answers.setdefault(correlation, []).append(decoded(message))
        assert b.bridge.connections == 3
        board = b.running.daemon.sims["sim1"].received
        moves = [r.data for r in list(board) if b"X1.25" in r.data]
    assert all("result" not in answer for answer in answers[b"limited"]), answers
    again = [answer for answer in answers[b"limited"] if not rate_limited(answer)]
    assert all(already_refused(answer) for answer in again), again
    assert "result" in answers[b"again"][0], answers
    assert len(moves) == 1, moves


async def test_a_new_daemon_does_not_run_commands_held_for_the_last_one(
    tmp_path: Path, broker: Broker
) -> None:
    """A daemon's first connection starts clean: the request ids the last process ran went
    with it, so what its session held (sent to it or redelivered) must not run now."""
    expiry = Properties(PacketTypes.CONNECT)  # type: ignore[no-untyped-call]
    expiry.SessionExpiryInterval = 30
    last = aiomqtt.Client(
        "127.0.0.1",
        broker.port,
        identifier="hostd-test-h1",  # the bridge's, below
        protocol=aiomqtt.ProtocolVersion.V5,
        properties=expiry,
        timeout=WAIT,
    )
    async with last:  # the last daemon: subscribed, then gone; the broker keeps its session
        await last.subscribe(topics.command_filter("test/h1"), qos=1)
    async with watching_broker(broker, "test/h1/online") as caller:
        await caller.client.subscribe(REPLIES, qos=1)
        await caller.send(COMMAND, {}, b"held", reply_to=REPLIES)
        async with bridged(tmp_path, broker, **SETTINGS) as b:
            await caller.state("test/h1/online", lambda payload: payload == "online")
            replies = await every_reply(caller)
            assert b.bridge.connections == 1
    assert [c for c, _ in replies] == [b"last"]


async def test_a_command_from_a_clock_ahead_is_not_run_again_when_it_comes_again_later(
    tmp_path: Path, broker: Broker
) -> None:
    """A command runs once for as long as a copy of it could pass the age check: until its
    own `sent_at` + command_max_age, past max_age after it ran when the caller's clock is
    ahead (a copy redelivered on a resumed session carries the same `sent_at`)."""
    now = [time.time()]  # the bridge's wall clock, moved on by the test

    async with (
        bridged(tmp_path, broker, wall=lambda: now[0], command_max_age=5, **SETTINGS),
        watching_broker(broker, "test/h1/online") as caller,
    ):
        await caller.state("test/h1/online", lambda payload: payload == "online")
        ahead = {"request_id": "ahead", "sent_at": now[0] + 4}  # within the 5 s
        first = await caller.request(COMMAND, {}, b"first", **ahead)
        assert "result" in first, first
        now[0] += 6  # past max_age since it ran; its sent_at only 2 s ago
        again = await caller.request(COMMAND, {}, b"again", **ahead)
        assert already_run(again), again
        now[0] += 4  # 6 s past its sent_at: too old to run, whatever its id
        late = await caller.request(COMMAND, {}, b"late", **ahead)
        assert late["error"]["code"] == -32002 and "s ago" in late["error"]["message"], late


async def test_commands_held_for_the_bridge_outlive_a_restart_of_a_persistent_broker(
    tmp_path: Path,
) -> None:
    """A broker that saves its sessions (mosquitto `persistence true`) sends, after its
    restart, the commands it held for the away bridge: they run once. mosquitto saves a
    session only if its last connection did not start clean (src/persist_write.c,
    `persist__client_save`), so the outage here comes on the bridge's second connection,
    as any outage past the daemon's first does."""
    directory = tmp_path / "broker"
    directory.mkdir()
    broker = Broker(directory, persistence=True)
    await broker.start()
    try:
        async with cable(broker) as hop, bridged(tmp_path, broker, url=hop.url, **SETTINGS) as b:
            async with watching_broker(broker, "test/h1/online") as caller:
                await caller.state("test/h1/online", lambda payload: payload == "online")
                await away(b, hop, caller)
                await hop.plug()
                await caller.state("test/h1/online", lambda payload: payload == "online")
                assert b.bridge.connections == 2
                await away(b, hop, caller)
                sent = [f"c{i}".encode() for i in range(5)]
                for correlation in sent:
                    await caller.send(COMMAND, {}, correlation, reply_to=REPLIES)
            await broker.stop()  # saves the bridge's session, its commands with it
            await broker.start()
            async with watching_broker(broker, "test/h1/online") as caller:
                await caller.client.subscribe(REPLIES, qos=1)
                await hop.plug()
                replies = await every_reply(caller)
            assert b.bridge.connections == 3
    finally:
        await broker.stop()
    assert once(replies, sent), replies
