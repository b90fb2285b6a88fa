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
comes again too: its `request_id` is then refused as already run.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Final

import aiomqtt
from paho.mqtt.properties import Properties
from paho.mqtt.subscribeoptions import SubscribeOptions

from hostd.api import rpc
from hostd.api.mqtt import topics
from hostd.api.mqtt.config import MqttConfig
from hostd.api.mqtt.outbox import Outbox

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
        # Request ids run, each until no copy of its command could pass `_stale` (wall time).
        self._seen: dict[str, float] = {}
        self._log = log
        unknown = sorted(set(config.allow) - set(methods))
        if unknown:
            self._log.warning("mqtt allow names unknown methods; ignored", methods=unknown)

    def cancel_all(self) -> None:
        """The bridge is stopping: the daemon's machines are gone."""
        for task in self.running:
            task.cancel()

    async def subscribe(self, client: aiomqtt.Client) -> None:
        # Retain as published: a retained command is seen as retained even when it arrives
        # live, so that none is ever run (it would run again on every reconnect).
        options = SubscribeOptions(qos=1, retainAsPublished=True)
        await client.subscribe(topics.command_filter(self.prefix), options=options)

    async def receive_loop(self, client: aiomqtt.Client, commands: asyncio.TaskGroup) -> None:
        """The commands, once `subscribe` has been answered; each acknowledged once taken."""
        async for message in client.messages:
            try:
                self._command(message, commands)
            except Exception:  # one odd message must never stop the bridge
                self._log.exception("mqtt message could not be handled", topic=str(message.topic))
            finally:
                # Taken: its request_id is seen (when it runs), so the broker may forget it.
                # Always, even for one that failed: unacknowledged, it would hold one of the
                # broker's in-flight places until the next connection, and come again there.
                client._client.ack(message.mid, message.qos)

    def _command(self, message: aiomqtt.Message, commands: asyncio.TaskGroup) -> None:
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
            refusal = (rpc.INVALID_REQUEST, "payload is not bytes")
        if refusal is not None:
            self._refuse(said, topic, caller, request_id, reply_to, correlation, refusal)
            return
        assert isinstance(payload, bytes)
        # A copy (a redelivery, a replay) passes the age check until `sent_at` + max_age: one
        # sent from a clock ahead of ours, later than max_age after it ran.
        sent = _sent_at(user)
        self._seen[request_id] = max(self._wall(), sent) + self.config.command_max_age
        task = commands.create_task(
            self._run_command(caller, machine, method, payload, reply_to, correlation)
        )
        self.running.add(task)
        task.add_done_callback(self.running.discard)

    def _refusal(
        self,
        message: aiomqtt.Message,
        method: str,
        reply_to: str | None,
        user: Mapping[str, str],
    ) -> tuple[int, str] | None:
        """Why this command does not run, or None: each check costs no parsing of the payload."""
        config = self.config
        payload = message.payload
        if message.retain:
            return (
                rpc.INVALID_REQUEST,
                "retained commands are never run; clear the retained message",
            )
        if not self._bucket.take():
            return (RATE_LIMITED, f"over {config.command_rate:g} commands/s; try again later")
        if reply_to is not None:
            problem = topics.response_topic_problem(self.prefix, reply_to)
            if problem is not None:
                return (rpc.INVALID_REQUEST, problem)
        if not config.commands:
            return (rpc.METHOD_NOT_FOUND, "commands are off on this daemon ([mqtt] commands)")
        if method not in config.allow:
            return (rpc.METHOD_NOT_FOUND, f"method not allowed over MQTT: {method}")
        if isinstance(payload, bytes | bytearray) and len(payload) > config.max_payload:
            return (
                rpc.INVALID_REQUEST,
                f"payload over {config.max_payload} bytes ([mqtt] max_payload)",
            )
        return self._stale(user) or (
            (rpc.SERVER_FULL, f"{MAX_COMMANDS} commands running; try again later")
            if len(self.running) >= MAX_COMMANDS
            else None
        )

    def _stale(self, user: Mapping[str, str]) -> tuple[int, str] | None:
        """The command's id and time: missing, too old, from the future, or seen before."""
        max_age = self.config.command_max_age
        request_id = user.get(ID_PROPERTY)
        if not request_id or len(request_id) > MAX_REQUEST_ID:
            why = f"a command needs a {ID_PROPERTY} user property (1 to {MAX_REQUEST_ID} chars)"
            return (rpc.INVALID_REQUEST, why)
        sent = _sent_at(user)
        if not math.isfinite(sent):
            why = f"a command needs a {TIME_PROPERTY} user property: Unix time in seconds"
            return (rpc.INVALID_REQUEST, why)
        now = self._wall()
        age = now - sent
        if age > max_age:
            return (
                STALE,
                f"command sent {age:.1f} s ago, over {max_age:g} s ([mqtt] command_max_age)",
            )
        if age < -max_age:
            return (STALE, f"command sent {-age:.1f} s in the future: check the clocks")
        # Ids of commands run, while a copy could pass the checks above: one delivered twice
        # (QoS 1, a session resumed) or replayed runs once.
        self._seen = {i: until for i, until in self._seen.items() if until >= now}
        if request_id in self._seen:
            return (STALE, f"command {request_id} already run")
        return None

    def _refuse(
        self,
        said: Any,
        topic: str,
        caller: MqttCaller,
        request_id: str,
        reply_to: str | None,
        correlation: bytes | None,
        refusal: tuple[int, str],
    ) -> None:
        """Log it, and answer it: on its response topic when it has a usable one, else on
        `<prefix>/errors`. Never silent."""
        code, why = refusal
        said.warning("mqtt command refused", code=code, reason=why, reply_to=reply_to)
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
            self._log.warning(
                "mqtt event dropped: broker behind",
                bound=self.config.max_events,
                dropped=self.outbox.dropped,
            )

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
