"""The outbox: coalescing, bounded, rate-limited, republished after a reconnect."""

from __future__ import annotations

import pytest

from hostd.api.mqtt.outbox import Outbox, Outgoing

pytestmark = pytest.mark.asyncio  # the outbox's `ready` event wants a running loop


def taken(outbox: Outbox, now: float = 0.0) -> list[tuple[str, bytes]]:
    out = []
    while isinstance(item := outbox.take(now), Outgoing):
        outbox.published(item, now)
        out.append((item.topic, item.payload))
    return out


async def test_a_retained_topic_keeps_only_its_latest_state_however_long_the_broker_is_away() -> (
    None
):
    outbox = Outbox(max_events=10)
    for i in range(100_000):
        outbox.put("p/m/status", str(i).encode())
        outbox.put("p/m/job", str(i).encode())
    assert len(outbox) == 2
    assert taken(outbox) == [("p/m/status", b"99999"), ("p/m/job", b"99999")]


async def test_events_are_bounded_and_the_oldest_go_first() -> None:
    outbox = Outbox(max_events=3)
    for i in range(10):
        outbox.event("p/m/exception", str(i).encode())
    assert len(outbox) == 3 and outbox.dropped == 7
    assert [p for _, p in taken(outbox)] == [b"7", b"8", b"9"]


async def test_a_failed_event_past_the_bound_is_the_oldest_and_goes_first() -> None:
    """The broker went while an event was being published, and newer events filled the
    outbox meanwhile: past `max_events` the oldest goes, as for any event (docs/mqtt.md),
    and the failed one is the oldest. The newest are never the ones lost."""
    outbox = Outbox(max_events=3)
    outbox.event("p/m/exception", b"0")
    first = outbox.take(0.0)
    assert isinstance(first, Outgoing)
    for i in range(1, 4):
        outbox.event("p/m/exception", str(i).encode())
    outbox.failed(first)
    assert outbox.dropped == 1
    assert [p for _, p in taken(outbox)] == [b"1", b"2", b"3"]


async def test_a_limited_topic_waits_its_interval_and_then_sends_the_latest() -> None:
    outbox = Outbox()
    outbox.limit("s", 0.25)
    outbox.put("s", b"1")
    assert taken(outbox, now=10.0) == [("s", b"1")]
    outbox.put("s", b"2")
    outbox.put("s", b"3")
    assert outbox.take(10.1) == pytest.approx(0.15)
    assert taken(outbox, now=10.25) == [("s", b"3")]


async def test_an_unchanged_state_is_not_published_again_until_a_reconnect() -> None:
    outbox = Outbox()
    outbox.put("s", b"same")
    assert taken(outbox) == [("s", b"same")]
    outbox.put("s", b"same")
    assert taken(outbox) == []
    outbox.resend()
    assert taken(outbox) == [("s", b"same")]


async def test_a_failed_publication_is_kept_for_the_next_connection() -> None:
    outbox = Outbox()
    outbox.put("s", b"1")
    outbox.event("e", b"x", b"corr")
    event = outbox.take(0.0)
    assert isinstance(event, Outgoing) and event.correlation == b"corr"
    outbox.failed(event)
    state = outbox.take(0.0)
    assert isinstance(state, Outgoing) and state.topic == "e"
    assert taken(outbox) == [("s", b"1")]


async def test_a_lazy_payload_is_made_when_taken() -> None:
    outbox = Outbox()
    made: list[bytes] = []

    def make(payload: bytes) -> bytes:
        made.append(payload)
        return payload

    outbox.put("s", lambda: make(b"now"))
    outbox.put("s", lambda: make(b"later"))
    assert taken(outbox) == [("s", b"later")]
    assert made == [b"later"]
