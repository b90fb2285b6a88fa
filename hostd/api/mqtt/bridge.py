"""The MQTT bridge: one more transport onto the API's dispatcher and subscriptions.

This module is the connection: it connects, runs the two directions over
it, and reconnects. Out (`publishing.py`): every machine's notifications
through the outbox to retained topics and events. In (`commands.py`, with
`commands = true`): a message on `<prefix>/<machine>/cmd/<method>` run as a
request against the same method table as the socket.

Connection: reconnects with back-off (`reconnect_min` doubling to
`reconnect_max`); each new connection subscribes to the command topics
first, then republishes every retained topic, `online` first: a caller
that has seen `online` is heard.
The broker keeps `<prefix>/online` = `offline` as our last will; a clean
stop publishes it ourselves.

A command outlives a dropped connection: the broker keeps the bridge's session
for `command_max_age` after a drop (MQTT 5 Session Expiry Interval) and every
reconnect resumes it (no clean start), so the broker sends again what it had
not seen acknowledged; and a command is acknowledged only once the bridge has
taken it (`commands.py`), never as the client reads it. The first connection
of a daemon starts clean: a session the last process left is not its own to
resume (its `request_id`s are gone with it).
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import random
import ssl
import time
from collections.abc import Callable, Mapping
from typing import Final

import aiomqtt
import structlog
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from hostd.api import rpc
from hostd.api.methods import Api
from hostd.api.mqtt import topics
from hostd.api.mqtt.commands import Commands, acknowledge_when_taken
from hostd.api.mqtt.config import MqttConfig
from hostd.api.mqtt.outbox import Outbox, Outgoing
from hostd.api.mqtt.publishing import Publisher

log = structlog.get_logger(__name__)

# Incoming messages the client holds for us. Each is refused or started at once, without
# parsing. It is also our MQTT 5 Receive Maximum: the broker sends no more than that
# unacknowledged, and we acknowledge a command only once taken, so the queue never fills.
MAX_INCOMING: Final = 10_000
# How long a clean stop may spend telling the broker `offline`.
STOP_TIMEOUT: Final = 2.0
# Room in a packet, past the payload, for its topic and properties.
PACKET_HEADROOM: Final = 64 << 10


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
        self.prefix = config.prefix
        self.outbox = Outbox(config.max_events)
        self.connected = asyncio.Event()
        self.disconnected = asyncio.Event()
        self.disconnected.set()
        self.connections = 0  # successful connections so far
        self._password = password
        self._stopping = asyncio.Event()
        self._log = log.bind(broker=f"{config.host}:{config.port}", prefix=self.prefix)
        self._out = Publisher(config, api, self.outbox, clock, self._log)
        self._in = Commands(config, methods, self.outbox, self._log, clock, wall)

    def attach(self) -> None:
        """Subscribe to every machine's notifications; queue the state there is now.

        Call once, after `Api.attach()` (the daemon's machines exist).
        """
        self._out.attach()

    async def load_last_jobs(self) -> None:
        """Each machine's last job from the store, unless a newer one was published meanwhile
        (publishing.py)."""
        await self._out.load_last_jobs()

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
            self._in.cancel_all()  # stopping: the daemon's machines are gone

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
        client = aiomqtt.Client(
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
            # A new client each connection: paho's default (clean on a client's first
            # connect only) would start every one clean and drop the session the broker
            # kept for us. The daemon's first connection is clean (module docstring).
            clean_start=self.connections == 0,
        )
        acknowledge_when_taken(client)
        return client

    def _connect_properties(self) -> Properties:
        """MQTT 5 CONNECT: the broker sends us no packet over max_payload and its headroom
        (it drops those for us), so a huge payload never reaches our memory at all; it keeps
        our session (the commands for us it has not seen acknowledged) `command_max_age`
        past a drop, no longer: an older command would be refused anyway; and it sends no
        more than MAX_INCOMING unacknowledged, so aiomqtt's queue never drops one."""
        properties = Properties(PacketTypes.CONNECT)  # type: ignore[no-untyped-call]
        properties.MaximumPacketSize = self.config.max_payload + PACKET_HEADROOM
        properties.SessionExpiryInterval = math.ceil(self.config.command_max_age)
        properties.ReceiveMaximum = MAX_INCOMING
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
            await self._in.subscribe(client)
            self.connections += 1
            self.disconnected.clear()
            self.connected.set()
            self._log.info("mqtt connected", client_id=self.config.identifier)
            self.outbox.resend()
            async with asyncio.TaskGroup() as tg:
                publisher = tg.create_task(self._out.publish_loop(client, self._stopping))
                receiver = tg.create_task(self._in.receive_loop(client, commands))
                await self._stopping.wait()
                publisher.cancel()
                receiver.cancel()
            offline = Outgoing(topics.online(self.prefix), topics.OFFLINE, retain=True)
            with contextlib.suppress(aiomqtt.MqttError, TimeoutError):
                async with asyncio.timeout(STOP_TIMEOUT):
                    await self._out.publish(client, offline)

    def _down(self) -> None:
        if self.connected.is_set():
            self._log.info("mqtt disconnected")
        self.connected.clear()
        self.disconnected.set()
