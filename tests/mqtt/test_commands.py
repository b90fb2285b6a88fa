"""Commands over a real mosquitto, from the wrong side: retained, stale, replayed, misdirected,
oversized, flooded and malformed. Each is refused out loud, nothing moves, the bridge goes on."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Iterator, MutableMapping
from contextlib import contextmanager
from functools import partial
from pathlib import Path
from typing import Any

import pytest
from structlog.testing import capture_logs

from tests.daemon.conftest import Rpc
from tests.mqtt.conftest import WAIT, Broker, Watcher, bridged, decoded, watching
from tests.mqtt.test_bridge import acked, start_job, streaming

pytestmark = pytest.mark.asyncio

Logs = list[MutableMapping[str, Any]]


@contextmanager
def logs() -> Iterator[Logs]:
    with capture_logs() as captured:
        yield captured


async def logged(
    captured: Logs, check: Callable[[MutableMapping[str, Any]], bool], n: int = 1
) -> None:
    """Until `n` captured log events pass `check` (the bridge logs as it decides)."""
    async with asyncio.timeout(WAIT):
        while sum(1 for e in captured if check(e)) < n:  # noqa: ASYNC110 (a list, no event)
            await asyncio.sleep(0.02)


def refused(code: int) -> Callable[[MutableMapping[str, Any]], bool]:
    return lambda e: e["event"] == "mqtt command refused" and e["code"] == code


async def paused_job(rpc: Rpc) -> int:
    job_id = await start_job(rpc, 20_000)
    await acked(rpc, job_id, 20)
    await rpc.call("machine.feedhold", machine="sim1")
    await rpc.notification(
        lambda n: n["params"]["job"]["id"] == job_id and n["params"]["job"]["state"] == "paused"
    )
    return job_id


async def test_a_retained_command_never_runs_not_even_after_a_broker_restart(
    tmp_path: Path,
) -> None:
    directory = tmp_path / "broker"
    directory.mkdir()
    broker = Broker(directory, persistence=True)  # a retained command survives its restart
    await broker.start()
    try:
        with logs() as captured:
            async with bridged(tmp_path, broker, commands=True) as b:
                rpc = await b.running.client()
                await b.running.idle(rpc)
                job_id = await paused_job(rpc)
                async with watching(broker, "test/h1/online") as caller:
                    answer = await caller.request(
                        "test/h1/sim1/cmd/machine.cycle_start", {}, b"r1", retain=True
                    )
                assert answer["error"]["code"] == -32600
                assert "retained" in answer["error"]["message"]
                await broker.stop()
                await broker.start()
                # The reconnected bridge is handed the retained command again: refused again.
                await logged(captured, lambda e: "retained" in e.get("reason", ""), 2)
                assert b.bridge.connections == 2
                assert (await rpc.call("job.get", job=job_id))["state"] == "paused"
                await rpc.call("job.cancel", machine="sim1")
                await rpc.close()
    finally:
        await broker.stop()


async def test_a_command_needs_an_id_and_a_recent_time_and_runs_once(
    tmp_path: Path, broker: Broker
) -> None:
    async with bridged(tmp_path, broker, commands=True, command_max_age=5) as b:
        rpc = await b.running.client()
        await b.running.idle(rpc)
        job_id = await paused_job(rpc)
        async with watching(broker, "test/h1/online") as caller:
            topic = "test/h1/sim1/cmd/machine.cycle_start"
            old = await caller.request(topic, {}, b"o1", sent_at=time.time() - 60)
            assert old["error"]["code"] == -32002 and "ago" in old["error"]["message"]
            future = await caller.request(topic, {}, b"f1", sent_at=time.time() + 60)
            assert future["error"]["code"] == -32002 and "future" in future["error"]["message"]
            bare = await caller.request(topic, {}, b"b1", user=[("client_id", "old-tool")])
            assert bare["error"]["code"] == -32600 and "request_id" in bare["error"]["message"]
            untimed = await caller.request(topic, {}, b"u1", user=[("request_id", "x")])
            assert untimed["error"]["code"] == -32600 and "sent_at" in untimed["error"]["message"]
            nan = await caller.request(
                topic, {}, b"n1", user=[("request_id", "y"), ("sent_at", "nan")]
            )
            assert nan["error"]["code"] == -32600
            assert (await rpc.call("job.get", job=job_id))["state"] == "paused"
            # The same id twice (a QoS 1 redelivery, a replay): it runs once.
            cancel = "test/h1/sim1/cmd/job.cancel"
            first = await caller.request(cancel, {}, b"c1", request_id="once")
            assert first["result"]["state"] == "cancelled"
            again = await caller.request(cancel, {}, b"c2", request_id="once")
            assert again["error"]["code"] == -32002 and "already run" in again["error"]["message"]
        await rpc.close()


@pytest.mark.parametrize("commands", [True, False])
async def test_a_bad_response_topic_is_refused_on_the_errors_topic_and_the_bridge_goes_on(
    tmp_path: Path, broker: Broker, commands: bool
) -> None:
    async with bridged(tmp_path, broker, commands=commands) as b:
        rpc, job_id = await streaming(b)
        async with watching(broker, "test/h1/#") as caller:
            cancel = "test/h1/sim1/cmd/job.cancel"
            for reply_to in (
                "test/h1/replies/#",  # a wildcard: not a topic one may publish to
                "test/h1/+/x",
                "elsewhere/replies",  # outside the prefix
                "test/h1/sim1/cmd/job.cancel",  # one of ours: a reply would be a command
                "test/h1/sim1/status",
            ):
                await caller.send(cancel, {}, b"bad", reply_to=reply_to, request_id=reply_to)
                error = await caller.state("test/h1/errors", partial(request_id_is, reply_to))
                assert error["topic"] == cancel and error["client_id"] == "tester"
                assert error["error"]["code"] == -32600
                assert "response topic" in error["error"]["message"]
            assert (await rpc.call("job.get", job=job_id))["state"] == "running"
            # Still there, with the same connection: a good request is answered.
            answer = await caller.request(cancel, {}, b"good")
        if commands:
            assert answer["result"]["state"] == "cancelled"
        else:
            assert "commands are off" in answer["error"]["message"]
            await rpc.call("job.cancel", machine="sim1")
        assert b.bridge.connections == 1
        await rpc.close()


def request_id_is(request_id: str, payload: Any) -> bool:
    return bool(payload["request_id"] == request_id)


async def test_an_oversized_payload_is_refused_unread_or_never_sent_by_the_broker(
    tmp_path: Path, broker: Broker
) -> None:
    with logs() as captured:
        async with bridged(tmp_path, broker, commands=True, max_payload=4096) as b:
            rpc, job_id = await streaming(b)
            async with watching(broker, "test/h1/online") as caller:
                cancel = "test/h1/sim1/cmd/job.cancel"
                over = b'{"x": "' + b"a" * 5000 + b'"}'
                answer = await caller.request(cancel, over, b"o1")
                assert answer["error"]["code"] == -32600
                assert "payload over 4096 bytes" in answer["error"]["message"]
                # Far past the maximum packet size the bridge gave the broker: the broker drops
                # it for us, so it never reaches the daemon's memory; the next one is answered.
                await caller.send(cancel, b"[" + b"0," * (4 << 20) + b"0]", b"huge")
                assert (await rpc.call("job.get", job=job_id))["state"] == "running"
                answer = await caller.request(cancel, {}, b"c1")
                assert answer["result"]["state"] == "cancelled"
            assert b.bridge.connections == 1
            await rpc.close()
    too_big = [e for e in captured if "payload over" in e.get("reason", "")]
    assert len(too_big) == 1  # the 4 MiB one never arrived: nothing to refuse


async def test_a_flood_past_the_rate_is_refused_out_loud_never_dropped(
    tmp_path: Path, broker: Broker
) -> None:
    settings: dict[str, Any] = {
        "commands": True,
        "allow": ["daemon.info"],
        "command_rate": 1,
        "command_burst": 5,
        "max_events": 1000,
    }
    with logs() as captured:
        async with bridged(tmp_path, broker, **settings) as b:
            async with watching(broker, "test/h1/online") as caller:
                # A caller waits for `online`: before the bridge subscribes, the broker drops
                # a command (no subscriber) and nothing can answer it. The flood went out as
                # the bridge started, and under load its first command was lost so, once.
                await caller.state("test/h1/online", lambda payload: payload == "online")
                topic = "test/h1/sim1/cmd/daemon.info"
                sent = 300
                started = time.monotonic()
                replies = "test/h1/replies/flood"
                await caller.client.subscribe(replies, qos=1)
                for i in range(sent):
                    await caller.send(topic, {}, str(i).encode(), reply_to=replies)
                answers = await replies_to(caller, replies, sent)
            assert b.bridge.connections == 1
    ran = [a for a in answers.values() if "result" in a]
    limited = [a for a in answers.values() if a.get("error", {}).get("code") == -32001]
    assert len(ran) + len(limited) == sent  # every one answered, one way or the other
    assert 5 <= len(ran) < sent // 2
    assert "commands/s" in limited[0]["error"]["message"]
    # Every refusal is in the log, counted, without a line each: a flood logs at most a
    # record a second (the first in full, then how many more), not one a refusal.
    records = [e for e in captured if refused(-32001)(e)]
    assert sum(e.get("repeats", 1) for e in records) == len(limited)
    assert len(records) <= 2 + time.monotonic() - started


async def test_online_is_said_once_commands_are_heard(tmp_path: Path) -> None:
    """The bridge subscribes to its command topics before it publishes `online` (on every
    connection, the same code): a caller that sees `online` and commands at once is
    answered, where a broker drops a message no subscription matches, without a word."""
    directory = tmp_path / "broker"
    directory.mkdir()
    broker = Broker(directory, debug=True)  # every packet it receives, logged in order
    await broker.start()
    try:
        async with (
            watching(broker, "test/h1/online") as caller,  # before the bridge is
            bridged(tmp_path, broker, commands=True, allow=["daemon.info"]),
        ):
            await caller.state("test/h1/online", lambda payload: payload == "online")
            answer = await caller.request("test/h1/sim1/cmd/daemon.info", {}, b"now")
            assert "result" in answer, answer
    finally:
        await broker.stop()  # its log read to the end
    ours = [line for line in broker.log if "Received " in line and "from hostd-test-h1" in line]
    received = [
        "subscribe" if "SUBSCRIBE" in line else "online"
        for line in ours
        if "SUBSCRIBE" in line or "'test/h1/online'" in line
    ]
    assert received[:2] == ["subscribe", "online"], received


async def replies_to(caller: Watcher, topic: str, n: int) -> dict[bytes, Any]:
    """The first `n` replies on `topic`, by correlation data."""
    found: dict[bytes, Any] = {}
    while len(found) < n:
        message = await caller.next(lambda m: str(m.topic) == topic)
        found[getattr(message.properties, "CorrelationData", b"")] = decoded(message)
    return found


async def test_the_bridge_survives_any_message(tmp_path: Path, broker: Broker) -> None:
    async with bridged(tmp_path, broker, commands=True) as b:
        rpc, job_id = await streaming(b)
        async with watching(broker, "test/h1/online") as caller:
            cancel = "test/h1/sim1/cmd/job.cancel"
            for n, payload in enumerate(
                (b"\xff\xfe\x00garbage", b"{", b"null", b'"x"', b"{}" * 1000, b'{"a":' * 5000)
            ):
                answer = await caller.request(cancel, payload, f"g{n}".encode())
                assert answer["error"]["code"] in (-32700, -32600, -32602), answer
            for topic in ("test/h1/sim1/cmd/", "test/h1//cmd/job.cancel", "test/h1/sim1/cmd/a/b"):
                await caller.send(topic, {}, b"t")
            odd = [("client_id", "\u2603" * 1000), ("request_id", "r" * 500), ("sent_at", "1e400")]
            answer = await caller.request(cancel, {}, b"odd", user=odd)
            assert answer["error"]["code"] == -32600
            assert (await rpc.call("job.get", job=job_id))["state"] == "running"
            answer = await caller.request(cancel, {}, b"c1")
            assert answer["result"]["state"] == "cancelled"
        assert b.bridge.connections == 1
        await rpc.close()
