"""Out: every machine's notifications onto the broker's topics, through the outbox.

The bridge is a subscriber of `Api.subscriptions` like any socket client, one
subscription per machine and topic, whose `send` only puts the encoded
notification into the `Outbox` (a dictionary store and an event set: never
blocks, never waits on the broker). One publisher task empties the outbox
into the broker. So the machines' streaming path never touches the network,
and a broker that is slow, restarting or gone costs the daemon one payload
per topic of memory and nothing else.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable
from functools import partial
from typing import Any

import aiomqtt
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from hostd.api.methods import Api
from hostd.api.mqtt import topics
from hostd.api.mqtt.config import MqttConfig
from hostd.api.mqtt.outbox import Outbox, Outgoing
from hostd.machine.machine import Machine


class Publisher:
    """What the bridge publishes: the machines' state and events, in, and the outbox, out."""

    def __init__(
        self,
        config: MqttConfig,
        api: Api,
        outbox: Outbox,
        clock: Callable[[], float],
        log: Any,
    ) -> None:
        self.config = config
        self.api = api
        self.prefix = config.prefix
        self.outbox = outbox
        self._clock = clock
        self._log = log

    # --- in: notifications to the outbox ----------------------------------------

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

    # --- out: the outbox to the broker -------------------------------------------

    async def publish_loop(self, client: aiomqtt.Client, stopping: asyncio.Event) -> None:
        """The one task that publishes: empties the outbox into `client` until `stopping`."""
        outbox = self.outbox
        # Not `while True`: on Python 3.11 asyncio.wait_for (aiomqtt's publish) returns its
        # result and drops a cancel that comes as the broker's PUBACK does, and the loop would
        # then wait on `ready` for good, holding up the stop and its `offline`.
        while not stopping.is_set():
            item = outbox.take(self._clock())
            if isinstance(item, Outgoing):
                try:
                    await self.publish(client, item)
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

    async def publish(self, client: aiomqtt.Client, message: Outgoing) -> None:
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
