"""The MQTT bridge: one more transport onto the API's dispatcher and subscriptions.

Out: the bridge is a subscriber of `Api.subscriptions` like any socket client,
one subscription per machine and topic, whose `send` only puts the encoded
notification into the `Outbox` (a dictionary store and an event set: never
blocks, never waits on the broker). One publisher task empties the outbox
into the broker. So the machines' streaming path never touches the network,
and a broker that is slow, restarting or gone costs the daemon one payload
per topic of memory and nothing else.

In (with `commands = true`): a message on `<prefix>/<machine>/cmd/<method>`
is a request: its payload the params (a JSON object, `machine` implied by the
topic), run through `rpc.answer` against the same method table as the socket,
and its answer (a JSON-RPC response) published to the MQTT 5 response topic
with the request's correlation data. Only methods in `allow` run; every
command is logged with the caller's `client_id` user property. A command
outlives the connection it came on: a dropped broker never cancels a cancel
half-way (its reply waits in the outbox for the next connection).

Connection: reconnects with back-off (`reconnect_min` doubling to
`reconnect_max`); each new connection subscribes to the command topics
first, then republishes every retained topic, `online` first: a caller
that has seen `online` is heard.
The broker keeps `<prefix>/online` = `offline` as our last will; a clean
stop publishes it ourselves.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import math
import random
import ssl
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import partial
from typing import Any, Final

import aiomqtt
import structlog
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties
from paho.mqtt.subscribeoptions import SubscribeOptions

from hostd.api import rpc
from hostd.api.methods import Api
from hostd.api.mqtt import topics
from hostd.api.mqtt.config import MqttConfig
from hostd.api.mqtt.outbox import Outbox, Outgoing
from hostd.machine.machine import Machine

log = structlog.get_logger(__name__)

# Commands running at once; one more is answered SERVER_FULL and does not run.
MAX_COMMANDS: Final = 16
# Incoming messages the client holds for us. Each is refused or started at once, without
# parsing, so the queue only fills if the loop is starved; past it the client drops (logged).
MAX_INCOMING: Final = 10_000
# How long a clean stop may spend telling the broker `offline`.
STOP_TIMEOUT: Final = 2.0
SERVER_FULL: Final = -32000
# Past the command rate; a command too old, from the future, or already run.
RATE_LIMITED: Final = -32001
STALE: Final = -32002
# Who sent a command: MQTT does not say; callers name themselves in this user property.
CALLER_PROPERTY: Final = "client_id"
# Every command carries its own id and the (Unix) time it was sent, as user properties.
ID_PROPERTY: Final = "request_id"
TIME_PROPERTY: Final = "sent_at"
MAX_REQUEST_ID: Final = 128
# Room in a packet, past the payload, for its topic and properties.
PACKET_HEADROOM: Final = 64 << 10


@dataclass(frozen=True, slots=True)
class MqttCaller:
    """The `context` of a request that came over MQTT (rpc.current_context())."""

    client_id: str
    topic: str


class MqttBridge:
    """Publishes every machine's state to a broker; takes commands from it when allowed.

    Usage (service.py)::

        bridge = MqttBridge(config.mqtt, api, methods, password=...)
        bridge.attach()                 # once the daemon's machines exist
        task = asyncio.create_task(bridge.run())
        ...
        await bridge.close(task)        # publishes `offline`, disconnects
    """

    def __init__(
        self,
        config: MqttConfig,
        api: Api,
        methods: Mapping[str, rpc.Method],
        *,
        password: str | None = None,
        clock: Callable[[], float] = time.monotonic,
        wall: Callable[[], float] = time.time,
    ) -> None:
        self.config = config
        self.api = api
        self.methods = methods
        self.prefix = config.prefix
        self.outbox = Outbox(config.max_events)
        self.connected = asyncio.Event()
        self.disconnected = asyncio.Event()
        self.disconnected.set()
        self.connections = 0  # successful connections so far
        self._password = password
        self._clock = clock
        self._stopping = asyncio.Event()
        self._ids = itertools.count(1)
        self._commands: set[asyncio.Task[None]] = set()
        self._wall = wall
        self._bucket = TokenBucket(config.command_rate, config.command_burst, clock)
        self._seen: dict[str, float] = {}  # request ids run within command_max_age
        self._log = log.bind(broker=f"{config.host}:{config.port}", prefix=self.prefix)
        unknown = sorted(set(config.allow) - set(methods))
        if unknown:
            self._log.warning("mqtt allow names unknown methods; ignored", methods=unknown)

    # --- out: notifications to topics -----------------------------------------

    def attach(self) -> None:
        """Subscribe to every machine's notifications; queue the state there is now.

        Call once, after `Api.attach()` (the daemon's machines exist).
        """
        self.outbox.put(topics.online(self.prefix), topics.ONLINE)
        subs = self.api.subscriptions
        for machine in self.api.daemon.machines.values():
            mid = machine.id
            status = topics.machine_topic(self.prefix, mid, "status")
            job = topics.machine_topic(self.prefix, mid, "job")
            faults = topics.machine_topic(self.prefix, mid, "faults")
            exception = topics.machine_topic(self.prefix, mid, "exception")
            self.outbox.limit(status, self.config.status_interval)
            self.outbox.limit(job, self.config.status_interval)
            routes: list[tuple[str, Callable[[bytes], object]]] = [
                ("status", partial(self._retained, status)),
                ("supervisor", partial(self._refresh, status, machine)),
                ("job", partial(self._retained, job)),
                ("fault", partial(self._refresh_faults, faults, machine)),
                ("exception", partial(self._event, exception)),
            ]
            for name, send in routes:
                # One owner per route: Subscriptions sends each owner one copy.
                subs.add((self, mid, name), send, [name], mid)
            self.outbox.put(status, partial(self._status_now, machine))
            self.outbox.put(faults, partial(self._faults_now, machine))
            current = machine.current_job()
            if current is not None:
                now = {"machine": mid, "job": current.model_dump(mode="json")}
                self.outbox.put(job, topics.encode(now))
            if self.config.homeassistant:
                for topic, payload in topics.discovery(
                    self.config.discovery_prefix, self.prefix, mid, machine.config.dialect
                ):
                    self.outbox.put(topic, payload)

    async def load_last_jobs(self) -> None:
        """Each machine's last job from the store (say, `interrupted` by a restart), unless a
        newer one was published meanwhile: the retained job topic never shows a dead job as
        running."""
        store = self.api.daemon.store
        if store is None:
            return
        for mid in self.api.daemon.machines:
            job = topics.machine_topic(self.prefix, mid, "job")
            rows = await store.list_jobs(mid, 1)
            if rows and not self.outbox.holds(job):
                last = {"machine": mid, "job": rows[0].model_dump(mode="json")}
                self.outbox.put(job, topics.encode(last))

    def _retained(self, topic: str, line: bytes) -> None:
        self.outbox.put(topic, partial(topics.params_of, line))

    def _event(self, topic: str, line: bytes) -> None:
        self.outbox.event(topic, topics.params_of(line))

    def _refresh(self, topic: str, machine: Machine, line: bytes) -> None:
        """The supervisor changed (a link drop sends no status report): the snapshot again."""
        self.outbox.put(topic, partial(self._status_now, machine))

    def _refresh_faults(self, topic: str, machine: Machine, line: bytes) -> None:
        self.outbox.put(topic, partial(self._faults_now, machine))

    @staticmethod
    def _status_now(machine: Machine) -> bytes:
        """A status payload made at publication time: `report` empty, the snapshot current."""
        return topics.encode({"machine": machine.id, "report": {}, "snapshot": machine.snapshot()})

    @staticmethod
    def _faults_now(machine: Machine) -> bytes:
        faults = [f.to_json() for f in machine.faults.all()]
        return topics.encode({"machine": machine.id, "faults": faults})

    # --- the connection ---------------------------------------------------------

    async def run(self) -> None:
        """Connect, publish, take commands; reconnect with back-off, until `close()`."""
        delay = self.config.reconnect_min
        async with asyncio.TaskGroup() as commands:
            while not self._stopping.is_set():
                error: str | None = None
                before = self.connections
                try:
                    await self._session(commands)
                except* (aiomqtt.MqttError, OSError, ssl.SSLError) as group:
                    error = "; ".join(str(e) for e in group.exceptions)
                except* Exception as group:  # a bug here: logged, and the bridge goes on
                    self._log.error("mqtt bridge failed", exc_info=group)
                    error = "internal error"
                finally:
                    self._down()
                if self._stopping.is_set():
                    break
                if error is None:  # a clean session end without a stop: should not happen
                    error = "session ended"
                if self.connections > before:  # it was up: the first retry comes soon
                    delay = self.config.reconnect_min
                self._log.warning("mqtt broker unreachable", error=error, retry_in=round(delay, 2))
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(delay * random.uniform(0.8, 1.2)):
                        await self._stopping.wait()
                delay = min(delay * 2, self.config.reconnect_max)
            for task in self._commands:  # stopping: the daemon's machines are gone
                task.cancel()

    async def close(self, task: asyncio.Task[None]) -> None:
        """Stop: `offline` published (within STOP_TIMEOUT), a clean disconnect, `task` done."""
        self._stopping.set()
        try:
            async with asyncio.timeout(STOP_TIMEOUT + 1):
                await asyncio.shield(task)
        except TimeoutError:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    def _client(self, tls: ssl.SSLContext | None) -> aiomqtt.Client:
        config = self.config
        will = aiomqtt.Will(topics.online(self.prefix), topics.OFFLINE, qos=1, retain=True)
        return aiomqtt.Client(
            config.host,
            config.port,
            identifier=config.identifier,
            username=config.username,
            password=self._password,
            protocol=aiomqtt.ProtocolVersion.V5,
            will=will,
            keepalive=config.keepalive,
            timeout=config.publish_timeout,
            tls_context=tls,
            tls_insecure=config.tls_insecure if tls is not None else None,
            max_queued_incoming_messages=MAX_INCOMING,
            properties=self._connect_properties(),
        )

    def _connect_properties(self) -> Properties:
        """MQTT 5 CONNECT: the broker sends us no packet over max_payload and its headroom
        (it drops those for us), so a huge payload never reaches our memory at all."""
        properties = Properties(PacketTypes.CONNECT)  # type: ignore[no-untyped-call]
        properties.MaximumPacketSize = self.config.max_payload + PACKET_HEADROOM
        return properties

    def _tls_context(self) -> ssl.SSLContext | None:
        config = self.config
        if not config.tls:
            return None
        context = ssl.create_default_context(cafile=config.ca_file)
        if config.cert_file:
            context.load_cert_chain(config.cert_file, config.key_file)
        if config.tls_insecure:
            context.check_hostname = False
        return context

    async def _session(self, commands: asyncio.TaskGroup) -> None:
        tls = await asyncio.to_thread(self._tls_context)
        async with self._client(tls) as client:
            # Subscribed (the broker's SUBACK) before anything is published: a caller who
            # sees `online` and commands at once is heard. A broker drops, without a word,
            # a message that no subscription matches; `online` published first (the
            # publisher and the receiver used to start together) let one be lost so.
            await self._subscribe(client)
            self.connections += 1
            self.disconnected.clear()
            self.connected.set()
            self._log.info("mqtt connected", client_id=self.config.identifier)
            self.outbox.resend()
            async with asyncio.TaskGroup() as tg:
                publisher = tg.create_task(self._publish_loop(client))
                receiver = tg.create_task(self._receive_loop(client, commands))
                await self._stopping.wait()
                publisher.cancel()
                receiver.cancel()
            offline = Outgoing(topics.online(self.prefix), topics.OFFLINE, retain=True)
            with contextlib.suppress(aiomqtt.MqttError, TimeoutError):
                async with asyncio.timeout(STOP_TIMEOUT):
                    await self._publish(client, offline)

    def _down(self) -> None:
        if self.connected.is_set():
            self._log.info("mqtt disconnected")
        self.connected.clear()
        self.disconnected.set()

    async def _publish_loop(self, client: aiomqtt.Client) -> None:
        outbox = self.outbox
        # Not `while True`: on Python 3.11 asyncio.wait_for (aiomqtt's publish) returns its
        # result and drops a cancel that comes as the broker's PUBACK does, and the loop would
        # then wait on `ready` for good, holding up the stop and its `offline`.
        while not self._stopping.is_set():
            item = outbox.take(self._clock())
            if isinstance(item, Outgoing):
                try:
                    await self._publish(client, item)
                except (ValueError, TypeError) as exc:
                    # Not publishable at all (a bad topic): retrying it would stop the bridge.
                    self._log.error(
                        "mqtt message not publishable; dropped", topic=item.topic, error=str(exc)
                    )
                    continue
                except BaseException:
                    outbox.failed(item)
                    raise
                outbox.published(item, self._clock())
            elif item is None:
                await outbox.ready.wait()
            else:  # something is due in `item` seconds, unless something else comes first
                outbox.ready.clear()
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(item):
                        await outbox.ready.wait()

    async def _publish(self, client: aiomqtt.Client, message: Outgoing) -> None:
        properties = None
        if message.correlation is not None:
            properties = Properties(PacketTypes.PUBLISH)  # type: ignore[no-untyped-call]
            properties.CorrelationData = message.correlation
        await client.publish(
            message.topic,
            message.payload,
            qos=1,
            retain=message.retain,
            properties=properties,
            timeout=self.config.publish_timeout,
        )

    # --- in: commands ---------------------------------------------------------

    async def _subscribe(self, client: aiomqtt.Client) -> None:
        # Retain as published: a retained command is seen as retained even when it arrives
        # live, so that none is ever run (it would run again on every reconnect).
        options = SubscribeOptions(qos=1, retainAsPublished=True)
        await client.subscribe(topics.command_filter(self.prefix), options=options)

    async def _receive_loop(self, client: aiomqtt.Client, commands: asyncio.TaskGroup) -> None:
        async for message in client.messages:
            try:
                self._command(message, commands)
            except Exception:  # one odd message must never stop the bridge
                self._log.exception("mqtt message could not be handled", topic=str(message.topic))

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
        self._seen[request_id] = self._wall()
        task = commands.create_task(
            self._run_command(caller, machine, method, payload, reply_to, correlation)
        )
        self._commands.add(task)
        task.add_done_callback(self._commands.discard)

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
            (SERVER_FULL, f"{MAX_COMMANDS} commands running; try again later")
            if len(self._commands) >= MAX_COMMANDS
            else None
        )

    def _stale(self, user: Mapping[str, str]) -> tuple[int, str] | None:
        """The command's id and time: missing, too old, from the future, or seen before."""
        max_age = self.config.command_max_age
        request_id = user.get(ID_PROPERTY)
        if not request_id or len(request_id) > MAX_REQUEST_ID:
            why = f"a command needs a {ID_PROPERTY} user property (1 to {MAX_REQUEST_ID} chars)"
            return (rpc.INVALID_REQUEST, why)
        try:
            sent = float(user.get(TIME_PROPERTY, ""))
        except ValueError:
            sent = math.nan
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
        # Ids of commands run within max_age: one delivered twice (QoS 1) runs once.
        self._seen = {i: t for i, t in self._seen.items() if now - t <= max_age}
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
