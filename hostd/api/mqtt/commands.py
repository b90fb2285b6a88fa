"""In: commands from the broker, each run as a request on the socket's method table.

With `[mqtt] commands = true`, a message on `<prefix>/<machine>/cmd/<method>`
is a request: its payload the params (a JSON object, `machine` implied by the topic),
run through `rpc.answer` against the same method table as the socket, and
its answer (a JSON-RPC response) published to the MQTT 5 response topic
with the request's correlation data. Only methods in `allow` run; every
command is logged with the caller's `client_id` user property, and must
carry its own `request_id` and `sent_at`: one too old, from the future or
seen before does not run. A retained command never runs, and the rate is
bounded (`command_rate`, `command_burst`). A refused command is answered on
its response topic, or else on `<prefix>/errors`: never silent. A command
outlives the connection it came on: a dropped broker never cancels a cancel
half-way (its reply waits in the outbox for the next connection).

A command is acknowledged (PUBACK) once taken, run or refused, not as the client
reads it: one read but still queued in the client when the connection drops is
not acknowledged, and the broker sends it again on the next connection of the
session (bridge.py). One taken whose acknowledgement was lost with the connection
comes again too: its `request_id` is then refused as already run, or as already
refused when it was refused for a passing reason (the rate, 16 running, from the
future): told "try again later", its caller may have sent it again under a new id,
so the first copy must never run later, when it would pass.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import math
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Final, NamedTuple

import aiomqtt
from paho.mqtt.properties import Properties
from paho.mqtt.subscribeoptions import SubscribeOptions

from hostd.api import rpc
from hostd.api.mqtt import topics
from hostd.api.mqtt.config import MqttConfig
from hostd.api.mqtt.outbox import Outbox
from hostd.api.tally import Tally

# Commands running at once; one more is answered rpc.SERVER_FULL and does not run.
MAX_COMMANDS: Final = 16
# Past the command rate; a command too old, from the future, or already run.
RATE_LIMITED: Final = -32001
STALE: Final = -32002
# Who sent a command: MQTT does not say; callers name themselves in this user property.
CALLER_PROPERTY: Final = "client_id"
# Every command carries its own id and the (Unix) time it was sent, as user properties.
ID_PROPERTY: Final = "request_id"
TIME_PROPERTY: Final = "sent_at"
MAX_REQUEST_ID: Final = 128
# Request ids refused for a passing reason, kept at most (the oldest forgotten first): a flood
# is refused by the rate limit itself, so nothing else bounds them. A refused command comes
# again (its PUBACK lost) among what was in flight to us unacknowledged when the connection
# dropped, which the broker sends again, in order, before what it queued later (MQTT 5 4.4,
# 4.6): fewer than our Receive Maximum (bridge.MAX_INCOMING, 10,000) other commands are
# taken in between. About 3 MB at most (ids of 128 characters). docs/mqtt.md says more.
MAX_REFUSED: Final = 10_000


class Refusal(NamedTuple):
    """Why a command does not run. `passing`: a copy of it could run later (over the rate,
    too many running, sent from the future), so its request_id is kept as refused."""

    code: int
    message: str
    passing: bool = False


@dataclass(frozen=True, slots=True)
class MqttCaller:
    """The `context` of a request that came over MQTT (rpc.current_context())."""

    client_id: str
    topic: str


class Commands:
    """Takes each command the broker delivers: refused at once, or run as a task."""

    def __init__(
        self,
        config: MqttConfig,
        methods: Mapping[str, rpc.Method],
        outbox: Outbox,
        log: Any,
        clock: Callable[[], float],
        wall: Callable[[], float],
    ) -> None:
        self.config = config
        self.methods = methods
        self.prefix = config.prefix
        self.outbox = outbox
        self.running: set[asyncio.Task[None]] = set()
        self._ids = itertools.count(1)
        self._wall = wall
        self._bucket = TokenBucket(config.command_rate, config.command_burst, clock)
        # Request ids run, each until no copy of its command could pass `_stale` (wall time):
        # never forgotten sooner, and bounded by the rate (runs in the last 2 command_max_age).
        self._seen = RecentIds()
        # Request ids refused for a passing reason, as long (MAX_REFUSED of them at most).
        self._refused = RecentIds(MAX_REFUSED)
        self._log = log
        # A flood of refusals (past the rate, above all) is logged at most once a second.
        self._refusals = Tally(log, "mqtt command refused", clock=clock)
        self._dropped = Tally(log, "mqtt event dropped: broker behind", clock=clock)
        unknown = sorted(set(config.allow) - set(methods))
        if unknown:
            self._log.warning("mqtt allow names unknown methods; ignored", methods=unknown)

    @property
    def kept_refused(self) -> int:
        """How many request ids are kept as refused (MAX_REFUSED at most)."""
        return len(self._refused)

    def cancel_all(self) -> None:
        """The bridge is stopping: the daemon's machines are gone. Refusals still tallied
        are told now."""
        for task in self.running:
            task.cancel()
        self._refusals.flush()
        self._dropped.flush()

    async def subscribe(self, client: aiomqtt.Client) -> None:
        # Retain as published: a retained command is seen as retained even when it arrives
        # live, so that none is ever run (it would run again on every reconnect).
        options = SubscribeOptions(qos=1, retainAsPublished=True)
        await client.subscribe(topics.command_filter(self.prefix), options=options)

    async def receive_loop(self, client: aiomqtt.Client, commands: asyncio.TaskGroup) -> None:
        """The commands, once `subscribe` has been answered; each acknowledged once taken."""
        async for message in client.messages:
            try:
                self.take(message, commands)
            except Exception:  # one odd message must never stop the bridge
                self._log.exception("mqtt message could not be handled", topic=str(message.topic))
            finally:
                # Taken: its request_id is remembered (run, or refused for a passing reason),
                # so the broker may forget it.
                # Always, even for one that failed: unacknowledged, it would hold one of the
                # broker's in-flight places until the next connection, and come again there.
                client._client.ack(message.mid, message.qos)

    def take(self, message: aiomqtt.Message, commands: asyncio.TaskGroup) -> None:
        """One command, as delivered: refused at once, or started as a task in `commands`."""
        topic = str(message.topic)
        parsed = topics.parse_command(self.prefix, topic)
        if parsed is None:
            return
        machine, method = parsed
        properties = message.properties
        reply_to: str | None = getattr(properties, "ResponseTopic", None) or None
        correlation: bytes | None = getattr(properties, "CorrelationData", None)
        user = _user_properties(properties)
        caller = MqttCaller(user.get(CALLER_PROPERTY, "unknown")[:128], topic)
        request_id = user.get(ID_PROPERTY, "")[:MAX_REQUEST_ID]
        said = self._log.bind(
            caller=caller.client_id, machine=machine, method=method, request_id=request_id
        )
        payload = message.payload
        refusal = self._refusal(message, method, reply_to, user)
        if refusal is None and not isinstance(payload, bytes):
            refusal = Refusal(rpc.INVALID_REQUEST, "payload is not bytes")
        if refusal is not None:
            if refusal.passing:
                self._remember(self._refused, user)
            self._refuse(said, topic, caller, request_id, reply_to, correlation, refusal)
            return
        assert isinstance(payload, bytes)
        self._remember(self._seen, user)
        task = commands.create_task(
            self._run_command(caller, machine, method, payload, reply_to, correlation)
        )
        self.running.add(task)
        task.add_done_callback(self.running.discard)

    def _remember(self, ids: RecentIds, user: Mapping[str, str]) -> None:
        """Keep the command's request_id in `ids` while a copy of it (a redelivery, a replay)
        could pass the age check: until its `sent_at` + max_age, later than max_age from now
        when sent from a clock ahead of ours. Not without a valid id and time: such a copy
        is refused for lacking them."""
        request_id = user.get(ID_PROPERTY, "")
        sent = _sent_at(user)
        if 0 < len(request_id) <= MAX_REQUEST_ID and math.isfinite(sent):
            ids.add(request_id, max(self._wall(), sent) + self.config.command_max_age)

    def _refusal(
        self,
        message: aiomqtt.Message,
        method: str,
        reply_to: str | None,
        user: Mapping[str, str],
    ) -> Refusal | None:
        """Why this command does not run, or None: each check costs no parsing of the payload.

        The refusals that are not `passing` refuse any copy of the command for the same
        reason (a copy is as retained, as large, as old or older, its method and response
        topic the same, the config the same while the daemon runs): their ids are not kept."""
        config = self.config
        payload = message.payload
        if message.retain:
            return Refusal(
                rpc.INVALID_REQUEST,
                "retained commands are never run; clear the retained message",
            )
        if not self._bucket.take():
            why = f"over {config.command_rate:g} commands/s; try again later"
            return Refusal(RATE_LIMITED, why, passing=True)
        if reply_to is not None:
            problem = topics.response_topic_problem(self.prefix, reply_to)
            if problem is not None:
                return Refusal(rpc.INVALID_REQUEST, problem)
        if not config.commands:
            return Refusal(
                rpc.METHOD_NOT_FOUND, "commands are off on this daemon ([mqtt] commands)"
            )
        if method not in config.allow:
            return Refusal(rpc.METHOD_NOT_FOUND, f"method not allowed over MQTT: {method}")
        if isinstance(payload, bytes | bytearray) and len(payload) > config.max_payload:
            return Refusal(
                rpc.INVALID_REQUEST,
                f"payload over {config.max_payload} bytes ([mqtt] max_payload)",
            )
        return self._stale(user) or (
            Refusal(rpc.SERVER_FULL, f"{MAX_COMMANDS} commands running; try again later", True)
            if len(self.running) >= MAX_COMMANDS
            else None
        )

    def _stale(self, user: Mapping[str, str]) -> Refusal | None:
        """The command's id and time: missing, too old, from the future, or seen before
        (run, or refused for a passing reason)."""
        max_age = self.config.command_max_age
        request_id = user.get(ID_PROPERTY)
        if not request_id or len(request_id) > MAX_REQUEST_ID:
            why = f"a command needs a {ID_PROPERTY} user property (1 to {MAX_REQUEST_ID} chars)"
            return Refusal(rpc.INVALID_REQUEST, why)
        sent = _sent_at(user)
        if not math.isfinite(sent):
            why = f"a command needs a {TIME_PROPERTY} user property: Unix time in seconds"
            return Refusal(rpc.INVALID_REQUEST, why)
        now = self._wall()
        age = now - sent
        if age > max_age:
            return Refusal(
                STALE,
                f"command sent {age:.1f} s ago, over {max_age:g} s ([mqtt] command_max_age)",
            )
        if age < -max_age:
            # Passing: a copy delivered once our clock has caught up would pass.
            why = f"command sent {-age:.1f} s in the future: check the clocks"
            return Refusal(STALE, why, passing=True)
        # Ids of commands run, or refused for a passing reason, while a copy could pass the
        # checks above: one delivered twice (QoS 1, a session resumed) or replayed runs once,
        # and one refused, its caller told to try again later, never runs.
        if self._seen.holds(request_id, now):
            return Refusal(STALE, f"command {request_id} already run")
        if self._refused.holds(request_id, now):
            return Refusal(STALE, f"command {request_id} already refused")
        return None

    def _refuse(
        self,
        said: Any,
        topic: str,
        caller: MqttCaller,
        request_id: str,
        reply_to: str | None,
        correlation: bytes | None,
        refusal: Refusal,
    ) -> None:
        """Log it (at most once a second in a flood, with how many: `Tally`), and answer it:
        on its response topic when it has a usable one, else on `<prefix>/errors`. Never
        silent."""
        code, why = refusal.code, refusal.message
        self._refusals.warning(said, code=code, reason=why, reply_to=reply_to)
        usable = (
            reply_to is not None and topics.response_topic_problem(self.prefix, reply_to) is None
        )
        data = {"allowed": list(self.config.allow)} if code == rpc.METHOD_NOT_FOUND else None
        if usable and reply_to is not None:
            self._answer(reply_to, rpc.encode_error(code, why, None, data), correlation)
            return
        error = {"code": code, "message": why}
        note = {
            "topic": topic,
            "client_id": caller.client_id,
            "request_id": request_id,
            "error": error,
        }
        self._answer(topics.errors(self.prefix), topics.encode(note))

    def _answer(self, topic: str, payload: bytes, correlation: bytes | None = None) -> None:
        """An event for the broker; one pushed out at the `max_events` bound is logged."""
        before = self.outbox.dropped
        self.outbox.event(topic, payload, correlation)
        if self.outbox.dropped > before:
            self._dropped.warning(bound=self.config.max_events, dropped=self.outbox.dropped)

    async def _run_command(
        self,
        caller: MqttCaller,
        machine: str,
        method: str,
        payload: bytes,
        reply_to: str | None,
        correlation: bytes | None,
    ) -> None:
        said = self._log.bind(caller=caller.client_id, machine=machine, method=method)
        said.info("mqtt command", reply_to=reply_to)
        request_id = next(self._ids)
        # The payload alone is parsed, by the socket's own strict rules, then made a request.
        parsed = rpc.decode(payload.strip() or b"{}", max_batch=1)
        params = parsed.message
        answer: bytes | None
        if parsed.reply is not None:
            answer = parsed.reply
        elif not isinstance(params, dict):
            why = "invalid params: the payload must be a JSON object (by name)"
            answer = rpc.encode_error(rpc.INVALID_PARAMS, why, request_id)
        elif self._takes_machine(method) and params.setdefault("machine", machine) != machine:
            why = "invalid params: machine differs from the topic's"
            answer = rpc.encode_error(rpc.INVALID_PARAMS, why, request_id)
        else:
            request = {"jsonrpc": "2.0", "id": request_id, "method": method, "params": params}
            answer = await rpc.answer(rpc.Incoming(request, 1), self.methods, caller)
        self._reply(said, reply_to, correlation, answer)

    def _takes_machine(self, method: str) -> bool:
        entry = self.methods.get(method)
        model = None if entry is None else entry.params_model
        return model is not None and "machine" in model.model_fields

    def _reply(
        self,
        said: Any,
        reply_to: str | None,
        correlation: bytes | None,
        answer: bytes | None,
    ) -> None:
        error = _error_code(answer)
        if error is None:
            said.info("mqtt command done")
        else:
            said.warning("mqtt command failed", code=error)
        if reply_to and answer is not None:
            self._answer(reply_to, answer, correlation)


def acknowledge_when_taken(client: aiomqtt.Client) -> None:
    """Have `client` acknowledge a message only when `receive_loop` has taken it.

    paho acknowledges a QoS 1 message as it reads it, before aiomqtt's queue hands it
    to us, and aiomqtt's message iterator ends at a disconnect with that queue not
    empty: read, acknowledged, never taken, a command was lost with the client.
    aiomqtt (2.5) has no manual acknowledgement of its own; its paho client (`_client`,
    private) has: set before `connect`, since a resumed session's commands come
    right after the CONNACK.
    """
    client._client.manual_ack_set(True)


def _sent_at(user: Mapping[str, str]) -> float:
    """The command's `sent_at` (Unix seconds), NaN when missing or not a number."""
    try:
        return float(user.get(TIME_PROPERTY, ""))
    except ValueError:
        return math.nan


def _user_properties(properties: Properties | None) -> dict[str, str]:
    """The message's user properties (the first of each name), as strings."""
    found: dict[str, str] = {}
    for pair in getattr(properties, "UserProperty", None) or []:
        if isinstance(pair, tuple) and len(pair) == 2:
            found.setdefault(str(pair[0]), str(pair[1]))
    return found


class RecentIds:
    """Request ids, each kept until a wall time; `bound` of them at most, the oldest added
    forgotten first. In the order added, so that the expired ones at the front go as a
    lookup passes (each id added is forgotten once: O(1) a call, amortized); an expired one
    behind a later one stays until it comes to the front, but is not held."""

    def __init__(self, bound: int | None = None) -> None:
        self._bound = bound
        self._until: OrderedDict[str, float] = OrderedDict()

    def __len__(self) -> int:
        return len(self._until)

    def add(self, request_id: str, until: float) -> None:
        """Keep `request_id` until `until` (or as long as it was kept), as the newest."""
        kept = self._until.pop(request_id, until)
        self._until[request_id] = max(kept, until)
        if self._bound is not None and len(self._until) > self._bound:
            self._until.popitem(last=False)

    def holds(self, request_id: str, now: float) -> bool:
        """Whether `request_id` is kept at `now`."""
        ids = self._until
        while ids:
            first, until = next(iter(ids.items()))
            if until >= now:
                break
            del ids[first]
        kept = ids.get(request_id)
        return kept is not None and kept >= now


class TokenBucket:
    """`rate` a second, `burst` at once: whether one more may go now."""

    def __init__(self, rate: float, burst: int, clock: Callable[[], float]) -> None:
        self._rate = rate
        self._burst = float(burst)
        self._tokens = float(burst)
        self._clock = clock
        self._at = clock()

    def take(self) -> bool:
        now = self._clock()
        self._tokens = min(self._burst, self._tokens + (now - self._at) * self._rate)
        self._at = now
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            return True
        return False


def _error_code(answer: bytes | None) -> int | None:
    if answer is None or b'"error"' not in answer:
        return None
    try:
        code = json.loads(answer).get("error", {}).get("code")
    except (ValueError, AttributeError):
        return None
    return code if isinstance(code, int) else None
