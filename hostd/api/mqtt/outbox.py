"""Between the machines and the broker: bounded, coalescing, never blocking the producer.

Machines produce on their streaming path (a Hub callback, through the API's
subscriptions); the broker may be slow, restarting or gone for hours. So:

- A retained topic (status, job, faults, online, discovery) keeps only its
  latest payload. Putting a newer one replaces the older, published or not:
  a topic is at most one entry however fast it changes and however long the
  broker is away. Its memory is one payload per topic.
- A payload may be a callable, made only when it is taken (a snapshot asked
  for at publication time, not at every status report).
- A retained topic may have a minimum interval between two publications
  (status, job): changes in between are coalesced into the latest.
- Events (exceptions, command replies) are a FIFO of at most `max_events`;
  past it the oldest is dropped and counted.
- After a reconnect every retained topic is published again (`resend`): the
  broker may have lost them.
- A payload equal to the one last published on its topic is not published again.

No I/O and no clock of its own: the bridge says what time it is.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

Payload = bytes | Callable[[], bytes | None]


@dataclass(frozen=True, slots=True)
class Outgoing:
    topic: str
    payload: bytes
    retain: bool
    # MQTT 5 correlation data of a command reply; None for everything else.
    correlation: bytes | None = None


@dataclass(slots=True)
class _Event:
    topic: str
    payload: bytes
    correlation: bytes | None


class Outbox:
    def __init__(self, max_events: int = 100) -> None:
        self._latest: dict[str, Payload] = {}  # retained topic -> its newest payload
        self._dirty: dict[str, None] = {}  # retained topics not yet published (ordered)
        self._published: dict[str, bytes] = {}  # retained topic -> payload last published
        self._interval: dict[str, float] = {}  # retained topic -> minimum seconds apart
        self._last: dict[str, float] = {}  # retained topic -> when last published
        self._events: deque[_Event] = deque()
        self._max_events = max_events
        self.dropped = 0  # events dropped at the bound, ever
        self.ready = asyncio.Event()  # something may be due

    def __len__(self) -> int:
        """Entries held: one per retained topic, plus the events waiting."""
        return len(self._latest) + len(self._events)

    def holds(self, topic: str) -> bool:
        """Whether `topic` has a retained state here (published or not)."""
        return topic in self._latest

    def limit(self, topic: str, interval: float) -> None:
        """Publish `topic` at most every `interval` seconds."""
        self._interval[topic] = interval

    def put(self, topic: str, payload: Payload) -> None:
        """The newest retained state of `topic`. Never blocks, never grows past one per topic."""
        self._latest[topic] = payload
        self._dirty[topic] = None
        self.ready.set()

    def event(self, topic: str, payload: bytes, correlation: bytes | None = None) -> None:
        """A message that is not retained; the oldest goes when `max_events` wait."""
        if len(self._events) >= self._max_events:
            self._events.popleft()
            self.dropped += 1
        self._events.append(_Event(topic, payload, correlation))
        self.ready.set()

    def resend(self) -> None:
        """Publish every retained topic again (a new connection: the broker may have lost them)."""
        self._published.clear()
        self._last.clear()
        for topic in self._latest:
            self._dirty[topic] = None
        if self._latest:
            self.ready.set()

    def take(self, now: float) -> Outgoing | float | None:
        """The next message to publish; else seconds until one is due, or None: nothing is.

        Events first (they are few and time-sensitive), then retained topics in
        the order they changed, skipping those inside their interval.
        """
        if self._events:
            e = self._events.popleft()
            return Outgoing(e.topic, e.payload, retain=False, correlation=e.correlation)
        wait: float | None = None
        for topic in list(self._dirty):
            due = self._last.get(topic, -1e18) + self._interval.get(topic, 0.0)
            if due > now:
                wait = due - now if wait is None else min(wait, due - now)
                continue
            del self._dirty[topic]
            made = self._latest[topic]
            payload = made() if callable(made) else made
            if payload is None or payload == self._published.get(topic):
                continue
            return Outgoing(topic, payload, retain=True)
        if wait is None:
            self.ready.clear()
        return wait

    def published(self, message: Outgoing, now: float) -> None:
        """The broker has it: remember what and when, for the interval and for duplicates."""
        if message.retain:
            self._published[message.topic] = message.payload
            self._last[message.topic] = now

    def failed(self, message: Outgoing) -> None:
        """Not delivered (the connection dropped): keep it for the next connection."""
        if message.retain:
            self._dirty.setdefault(message.topic, None)
        else:
            # Back at the front, as the oldest: past the bound the oldest goes, as in
            # `event` (docs/mqtt.md), and that is this one.
            self._events.appendleft(_Event(message.topic, message.payload, message.correlation))
            while len(self._events) > self._max_events:
                self._events.popleft()
                self.dropped += 1
        self.ready.set()
