"""Gates of the MQTT bridge that no test guarded: a hand mutation campaign on
hostd/api/mqtt/*.py changed one thing at a time (a bound doubled, a check dropped, a
flag flipped), and each test here is one the whole suite passed without. Each says, in
its docstring, what a fleet operator or a security reviewer would see go wrong, and the
change to the bridge it failed on.

The broker is a real mosquitto (conftest.py); a wall clock for `sent_at` is held by the
test where a bound is the point, so a command sent just past the bound is past it.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from pathlib import Path
from typing import Any, cast

import aiomqtt
import pytest
import structlog
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from hostd.api.methods import Api
from hostd.api.mqtt.commands import MAX_REFUSED
from hostd.api.mqtt.config import MqttConfig
from hostd.api.mqtt.outbox import Outbox, Outgoing
from hostd.api.mqtt.publishing import Publisher
from hostd.config import ConfigError
from tests.daemon.conftest import running_daemon
from tests.mqtt.conftest import WAIT, Bridged, Broker, Watcher, bridged, decoded, watching
from tests.mqtt.test_bridge import acked, ended, start_job, streaming
from tests.mqtt.test_commands import logged, logs
from tests.mqtt.test_config import config
from tests.mqtt.test_refused import MIDS, REPLIES, TOPIC, Bench

INFO = "test/h1/sim1/cmd/daemon.info"
SEND = "test/h1/sim1/cmd/machine.send"
CANCEL = "test/h1/sim1/cmd/job.cancel"


async def online(caller: Watcher) -> None:
    await caller.state("test/h1/online", lambda payload: payload == "online")


async def ready_to_move(b: Bridged, caller: Watcher) -> None:
    """Until the machine is idle and the bridge online: a command may move the board."""
    rpc = await b.running.client()
    await b.running.idle(rpc)
    await rpc.close()
    await online(caller)


def moves(b: Bridged, marker: bytes) -> list[bytes]:
    """The lines the simulated board got that carry `marker`."""
    return [r.data for r in list(b.running.daemon.sims["sim1"].received) if marker in r.data]


async def publish_bare(caller: Watcher, topic: str, payload: bytes, user: list[Any]) -> None:
    """An MQTT 5 command without a response topic (nor correlation data)."""
    properties = Properties(PacketTypes.PUBLISH)  # type: ignore[no-untyped-call]
    properties.UserProperty = user
    await caller.client.publish(topic, payload, qos=1, properties=properties)


def deliver(bench: Bench, request_id: str, payload: bytes = b"{}", retain: bool = False) -> None:
    """A command as the broker delivers it to `bench` (test_refused.py), with a reply topic
    and this payload, retained or not."""
    properties = Properties(PacketTypes.PUBLISH)  # type: ignore[no-untyped-call]
    properties.ResponseTopic = REPLIES
    properties.CorrelationData = request_id.encode()
    properties.UserProperty = [("request_id", request_id), ("sent_at", f"{bench.now:.3f}")]
    message = aiomqtt.Message(TOPIC, payload, 1, retain, next(MIDS), properties)
    bench.commands.take(message, bench.tasks)


def clocked(
    tmp_path: Path, broker: Broker, now: list[float], method: str
) -> contextlib.AbstractAsyncContextManager[Any]:
    """A bridge whose wall clock is `now[0]` (the test moves it), `command_max_age` 5 s,
    commands on, `method` alone allowed."""
    return bridged(
        tmp_path,
        broker,
        wall=lambda: now[0],
        command_max_age=5,
        commands=True,
        allow=[method],
    )


@pytest.mark.asyncio
async def test_a_command_just_past_command_max_age_is_refused_in_the_past_and_the_future(
    tmp_path: Path, broker: Broker
) -> None:
    """`command_max_age` is the bound, not a multiple of it: with 5 s, a command sent 6 s
    ago (held by a broker through an outage) or 6 s ahead of the daemon's clock is refused
    -32002; one 4 s old runs. Failed with the future bound 5 s looser (commands.py
    `_stale`, `age < -max_age - 5`), which the suite passed (its command from the future
    was 10 s past the bound); and with either bound at 2 x command_max_age."""
    now = [time.time()]  # the bridge's wall clock, held
    async with (
        clocked(tmp_path, broker, now, "daemon.info"),
        watching(broker, "test/h1/online") as caller,
    ):
        await online(caller)
        old = await caller.request(INFO, {}, b"old", sent_at=now[0] - 6)
        assert old["error"]["code"] == -32002 and "6.0 s ago" in old["error"]["message"], old
        ahead = await caller.request(INFO, {}, b"ahead", sent_at=now[0] + 6)
        assert ahead["error"]["code"] == -32002, ahead
        assert "in the future" in ahead["error"]["message"], ahead
        recent = await caller.request(INFO, {}, b"recent", sent_at=now[0] - 4)
        assert "result" in recent, recent


@pytest.mark.asyncio
async def test_a_request_id_run_is_refused_for_command_max_age_after_it_ran_even_re_stamped(
    tmp_path: Path, broker: Broker
) -> None:
    """A `request_id` already run is refused for at least `command_max_age` after it ran
    (docs/mqtt.md), whatever `sent_at` its copy carries: a caller's tool that retries a
    command under its old id with a fresh `sent_at` gets "already run", and the board gets
    the move once. Failed with the id kept only until its first `sent_at` + max_age
    (commands.py `_remember`): the command, 4 s old when it ran, ran again 2 s later."""
    now = [time.time()]  # the bridge's wall clock, moved on by the test
    async with (
        clocked(tmp_path, broker, now, "machine.send") as b,
        watching(broker, "test/h1/online") as caller,
    ):
        await ready_to_move(b, caller)
        move = {"line": "G0 X4.25"}
        first = await caller.request(SEND, move, b"first", request_id="retry", sent_at=now[0] - 4)
        assert "result" in first, first
        now[0] += 2  # 6 s past its first sent_at, 2 s after it ran
        again = await caller.request(SEND, move, b"again", request_id="retry", sent_at=now[0])
        assert again["error"] == {"code": -32002, "message": "command retry already run"}, again
        assert len(moves(b, b"X4.25")) == 1


@pytest.mark.asyncio
async def test_a_request_id_of_none_or_over_128_characters_never_moves_the_machine(
    tmp_path: Path, broker: Broker
) -> None:
    """A command's `request_id` is 1 to 128 characters (docs/mqtt.md), or it is refused
    -32600 and nothing moves: an empty one, or one too long to be remembered, would run
    every time it was replayed. Failed with the empty id let through, and with the 128
    bound dropped (commands.py `_stale`): the 200-character id's move then reached the
    board twice. The existing test's long id came with an unusable `sent_at` as well."""
    async with (
        bridged(tmp_path, broker, commands=True, allow=["machine.send"]) as b,
        watching(broker, "test/h1/online") as caller,
    ):
        await ready_to_move(b, caller)
        move = {"line": "G0 X3.5"}
        for n, request_id in enumerate(("", "r" * 200, "r" * 200)):
            user = [("request_id", request_id), ("sent_at", f"{time.time():.3f}")]
            answer = await caller.request(SEND, move, f"bad{n}".encode(), user=user)
            assert answer["error"]["code"] == -32600, answer
            assert "request_id" in answer["error"]["message"], answer
        longest = {"request_id": "r" * 128}
        assert "result" in await caller.request(SEND, move, b"longest", **longest)
        again = await caller.request(SEND, move, b"again", **longest)
        assert "already run" in again["error"]["message"], again
        assert len(moves(b, b"X3.5")) == 1


@pytest.mark.asyncio
async def test_the_payload_is_the_params_only_and_an_empty_one_is_no_params(
    tmp_path: Path, broker: Broker
) -> None:
    """The payload can name no method: `{"method": "machine.send", ...}` sent to an allowed
    `job.cancel` is that method's bad params (-32602), and the board gets nothing; and an
    empty payload (`mosquitto_pub -n`) is `{}`: it cancels the job. Failed with the method
    taken from the payload (the allow-list bypassed: the line reached the board) and with
    the empty payload parsed as it is (-32700: the operator's cancel did not cancel)."""
    async with bridged(tmp_path, broker, commands=True) as b:
        rpc = await b.running.client()
        await b.running.idle(rpc)
        async with watching(broker, "test/h1/online") as caller:
            await online(caller)
            smuggled = {"method": "machine.send", "line": "G0 X7.5"}
            answer = await caller.request(CANCEL, smuggled, b"smuggled")
            assert answer["error"]["code"] == -32602, answer
            job_id = await start_job(rpc, 20_000)
            await acked(rpc, job_id, 20)
            cancel = await caller.request(CANCEL, b"", b"empty")
            assert cancel["result"]["id"] == job_id, cancel
            assert cancel["result"]["state"] == "cancelled", cancel
        assert moves(b, b"X7.5") == []
        await rpc.close()


@pytest.mark.asyncio
async def test_a_command_without_a_response_topic_runs_and_only_a_refusal_is_published(
    tmp_path: Path, broker: Broker
) -> None:
    """A caller without a response topic (docs/mqtt.md: "the request runs, nothing is
    answered; a refusal is published on `<prefix>/errors`"): its cancel cancels the job,
    and the first message on `errors` is its later refusal, not the cancel's answer.
    Failed with the answer of a command run published on `errors` when it had no response
    topic, and with the response topic checked when there is none (the command was then
    dropped, unanswered and not run)."""
    async with bridged(tmp_path, broker, commands=True) as b:
        rpc, job_id = await streaming(b)
        async with watching(broker, "test/h1/errors") as caller:
            user = [("request_id", "bare-cancel"), ("sent_at", f"{time.time():.3f}")]
            await publish_bare(caller, CANCEL, b"{}", user)
            assert (await ended(rpc, job_id))["state"] == "cancelled"
            stale = [("request_id", "bare-stale"), ("sent_at", f"{time.time() - 600:.3f}")]
            await publish_bare(caller, CANCEL, b"{}", stale)
            first = await caller.next(lambda m: True)
            note = decoded(first)
            assert note["request_id"] == "bare-stale", note
            assert note["topic"] == CANCEL and note["error"]["code"] == -32002, note
        await rpc.close()


@pytest.mark.asyncio
async def test_retained_commands_cannot_push_a_refused_command_out_of_memory() -> None:
    """A command refused over the rate ("try again later") is kept as refused, so that a
    copy of it never runs once its caller may have sent it again. A flood of retained
    commands (refused at once, for good) must not push it out of the 10,000 kept: it is
    still "already refused" when its copy comes with the rate refilled. Failed with every
    refusal's id kept, not only the passing ones (commands.py `take`): the flood filled the
    bound and the refused command ran."""
    async with asyncio.TaskGroup() as tasks:
        bench = Bench(tasks)  # a burst of 1, the clocks held
        bench.send("ran")
        bench.send("limited")  # over the rate: told to try again later
        for i in range(MAX_REFUSED):
            deliver(bench, f"r{i}", retain=True)
        assert bench.commands.kept_refused == 1
        bench.now += 1.0  # the rate lets one more pass
        bench.send("limited")
        again = await bench.answer("limited")
        assert again["error"] == {"code": -32002, "message": "command limited already refused"}
        assert bench.runs == ["info"]


@pytest.mark.asyncio
async def test_a_bridge_idle_for_an_hour_lets_no_more_than_a_burst_through_at_once() -> None:
    """The command rate refills up to `command_burst`, no further: after an hour without
    a command, a flood of five runs two (the burst) and refuses the rest -32001. Failed
    with the cap dropped (commands.py `TokenBucket.take`): an hour's worth, 3,600
    commands, would have run at once."""
    async with asyncio.TaskGroup() as tasks:
        bench = Bench(tasks, burst=2)  # 1 command/s, bursts of 2
        bench.now += 3600.0
        for i in range(5):
            bench.send(f"b{i}")
        last = await bench.answer("b4")
        assert last["error"]["code"] == -32001, last
        assert bench.runs == ["info", "info"]


@pytest.mark.asyncio
async def test_a_payload_of_max_payload_bytes_runs_and_one_byte_more_is_refused() -> None:
    """`max_payload` (64 KiB by default) is the largest payload taken, not the smallest
    refused: a client that fills it exactly is answered with the result, one byte more
    with -32600 "payload over". Failed with the bound off by one (commands.py
    `_refusal`, `>=`)."""
    async with asyncio.TaskGroup() as tasks:
        bench = Bench(tasks, burst=2)
        limit = bench.commands.config.max_payload
        deliver(bench, "full", b"{" + b" " * (limit - 2) + b"}")
        assert "result" in await bench.answer("full")
        deliver(bench, "over", b"{" + b" " * (limit - 1) + b"}")
        over = await bench.answer("over")
        assert over["error"]["code"] == -32600 and "payload over" in over["error"]["message"]
        assert bench.runs == ["info"]


@pytest.mark.parametrize(
    ("mqtt", "problem"),
    [
        ({"allow": ["unsubscribe"]}, "cannot be called"),
        ({"allow": ["job.*"]}, "not a method name"),
        ({"allow": ["#"]}, "not a method name"),
        ({"topic_prefix": "$SYS/hostd"}, "leading \\$"),
        ({"topic_prefix": "/shop1/bench3"}, "leading \\$ or /"),
        ({"topic_prefix": "shop1//bench3"}, "empty levels"),
    ],
)
def test_a_config_that_would_misroute_commands_or_state_does_not_start(
    mqtt: dict[str, Any], problem: str
) -> None:
    """The daemon refuses, at start, an `allow` naming what is not one method (a wildcard
    would allow nothing, silently; `unsubscribe` needs a connection of its own) and a
    `topic_prefix` a fleet's `shop1/#` would not see (`$`: the broker's own topics) or that
    starts or holds an empty level. Failed with `unsubscribe` allowed, with any text taken
    as a method name, and with the prefix's first-level and `//` checks dropped
    (config.py)."""
    with pytest.raises(ConfigError, match=problem):
        config(**mqtt)


def test_by_default_only_hold_resume_and_cancel_may_be_commanded() -> None:
    """With `commands = true` and no `allow`, a broker's user can hold, resume and cancel,
    nothing else (docs/mqtt.md): not a line to the board. The existing test compared the
    default with the constant itself; this one failed with `machine.send` added to it."""
    assert config(commands=True).allow == ["machine.feedhold", "machine.cycle_start", "job.cancel"]


@pytest.mark.asyncio
async def test_state_is_retained_and_answers_are_not_and_all_of_it_goes_at_qos_1(
    tmp_path: Path, broker: Broker
) -> None:
    """Everything is published with QoS 1 (docs/mqtt.md), the state retained, a command's
    answer and a refusal on `errors` not: a retained answer would be handed to every later
    subscriber of the reply topic as if new. Failed with QoS 0 (publishing.py `publish`)
    and with every publication retained."""
    async with (
        bridged(tmp_path, broker, commands=True, allow=["daemon.info"]),
        watching(broker, "test/h1/#") as caller,
    ):
        kept = await caller.retained("test/h1/online", "test/h1/sim1/status")
        assert decoded(kept["test/h1/online"]) == "online"
        assert [message.qos for message in kept.values()] == [1, 1]
        reply_to = await caller.send(INFO, {}, b"q1")
        reply = await caller.next(lambda m: str(m.topic) == reply_to)
        assert "result" in decoded(reply)
        assert (reply.qos, reply.retain) == (1, False)
        await caller.send(INFO, {}, b"q2", reply_to="elsewhere/replies", request_id="q2")
        note = await caller.next(lambda m: str(m.topic) == "test/h1/errors")
        assert decoded(note)["request_id"] == "q2"
        assert (note.qos, note.retain) == (1, False)


@pytest.mark.asyncio
async def test_the_bridge_retries_a_vanished_broker_at_most_reconnect_max_apart(
    tmp_path: Path, broker: Broker
) -> None:
    """The reconnect back-off doubles from `reconnect_min` up to `reconnect_max`, no
    further: a broker back after a long outage is found within `reconnect_max` (not hours
    later), and the state is published again. Failed with the cap dropped (bridge.py
    `run`): the fourth retry already waited twice `reconnect_max`."""

    def unreachable(event: Any) -> bool:
        return bool(event["event"] == "mqtt broker unreachable")

    with logs() as captured:
        async with bridged(tmp_path, broker, reconnect_min=0.05, reconnect_max=0.2) as b:
            async with asyncio.timeout(WAIT):
                await b.bridge.connected.wait()
            await broker.stop()
            await logged(captured, unreachable, 6)
            delays = [e["retry_in"] for e in captured if unreachable(e)]
            assert max(delays) <= 0.2, delays
            await broker.start()
            async with watching(broker, "test/h1/online") as watcher:
                await online(watcher)
            assert b.bridge.connections == 2


@pytest.mark.asyncio
async def test_a_failed_publication_keeps_the_events_within_max_events() -> None:
    """An event whose publication failed (the broker vanished under it) goes back into the
    outbox, which still holds at most `max_events` events, the rest counted as dropped:
    memory stays flat over an outage. Failed with the bound not applied there
    (outbox.py `failed`)."""
    outbox = Outbox(max_events=2)
    outbox.event("p/replies/a", b"1", b"c1")
    outbox.event("p/replies/a", b"2", b"c2")
    taken = outbox.take(0.0)
    outbox.event("p/replies/a", b"3", b"c3")  # the broker goes while "1" is out
    assert not isinstance(taken, float | None)
    outbox.failed(taken)
    assert len(outbox) == 2 and outbox.dropped == 1


@pytest.mark.asyncio
async def test_a_controller_exception_is_published_once_and_not_retained(
    tmp_path: Path, broker: Broker
) -> None:
    """An alarm's exception report reaches `<prefix>/<machine>/exception`, not retained
    (docs/mqtt.md: an event, not a state). Failed with the exception route dropped
    (publishing.py `attach`): an alarm on the board said nothing on the broker."""
    async with bridged(tmp_path, broker) as b:
        rpc = await b.running.client()
        await b.running.idle(rpc)
        async with watching(broker, "test/h1/sim1/exception") as watcher:
            await rpc.call("machine.alarm", machine="sim1")
            message = await watcher.next(lambda m: True)
            assert decoded(message)["machine"] == "sim1" and message.retain is False
        await rpc.call("machine.clear", machine="sim1")
        await rpc.close()


@pytest.mark.asyncio
async def test_a_fault_that_comes_is_published_on_the_faults_topic(
    tmp_path: Path, broker: Broker
) -> None:
    """A fault raised while the daemon runs (line noise on the board: `lexical`) is on the
    retained faults topic, the whole table. Failed with the fault route dropped
    (publishing.py `attach`): the topic kept the table of the start, all clear."""
    async with bridged(tmp_path, broker) as b:
        rpc = await b.running.client()
        await b.running.idle(rpc)
        async with watching(broker, "test/h1/sim1/faults") as watcher:
            await watcher.retained("test/h1/sim1/faults")
            b.running.daemon.sims["sim1"].inject_garbage(b'{"r":{"broken"\n')
            await watcher.state(
                "test/h1/sim1/faults",
                lambda p: any(f["id"] == "lexical" and f["active"] for f in p["faults"]),
            )
        await rpc.close()


@pytest.mark.asyncio
async def test_home_assistant_is_told_of_each_machine_when_asked(
    tmp_path: Path, broker: Broker
) -> None:
    """With `homeassistant = true` each machine is a device found by MQTT discovery: its
    retained config names the machine's status topic and the daemon's `online` as its
    availability. Failed with the discovery messages never queued (publishing.py
    `attach`): Home Assistant never saw the machines."""
    async with (
        bridged(tmp_path, broker, homeassistant=True),
        watching(broker, "homeassistant/#") as watcher,
    ):
        topic = "homeassistant/sensor/test_h1_sim1/state/config"
        entity = decoded((await watcher.retained(topic))[topic])
        assert entity["state_topic"] == "test/h1/sim1/status"
        assert entity["availability_topic"] == "test/h1/online"


@pytest.mark.asyncio
async def test_a_restarted_daemon_publishes_the_last_job_it_has_on_record(
    tmp_path: Path, broker: Broker
) -> None:
    """The job topic of a daemon that starts again shows the machine's last job from its
    history (docs/mqtt.md: a job the last process's death interrupted shows
    `interrupted`, never `running`); here one that completed. Failed with the history not
    read at start (publishing.py `load_last_jobs`): no job topic at all."""
    async with running_daemon(tmp_path) as first:
        rpc = await first.client()
        await first.idle(rpc)
        job_id = await start_job(rpc, 5)
        assert (await ended(rpc, job_id))["state"] == "completed"
        await rpc.close()
    async with bridged(tmp_path, broker), watching(broker, "test/h1/sim1/job") as watcher:
        job = decoded((await watcher.retained("test/h1/sim1/job"))["test/h1/sim1/job"])
        assert job["job"]["id"] == job_id and job["job"]["state"] == "completed"


@pytest.mark.asyncio
async def test_an_answer_whose_publication_fails_is_kept_for_the_next_connection() -> None:
    """A command's answer being published when the broker connection drops is kept and
    published on the next connection (docs/mqtt.md: "its answer waits ... for the next
    connection"). Failed with the failed publication not put back (publishing.py
    `publish_loop`): the caller never heard whether its cancel ran."""
    config = MqttConfig.model_validate({"url": "mqtt://127.0.0.1:1", "topic_prefix": "test/h1"})
    outbox = Outbox()
    outbox.event("test/h1/replies/op", b'{"jsonrpc":"2.0","result":{},"id":1}', b"c1")
    publisher = Publisher(config, cast(Api, None), outbox, time.monotonic, structlog.get_logger())

    class Vanished:
        async def publish(self, *args: Any, **kwargs: Any) -> None:
            raise aiomqtt.MqttError("Disconnected during message iteration")

    with pytest.raises(aiomqtt.MqttError):
        await publisher.publish_loop(cast(aiomqtt.Client, Vanished()), asyncio.Event())
    kept = outbox.take(0.0)
    assert isinstance(kept, Outgoing), kept
    assert (kept.topic, kept.correlation) == ("test/h1/replies/op", b"c1")
