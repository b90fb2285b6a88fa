"""The API's fan-out: one encoding for every subscriber, the right subscribers after any change."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from hostd.api.methods import Subscriptions, console_notification
from hostd.api.rpc import encode_notification
from hostd.machine.events import Console


@given(
    text=st.text(),  # every code point: quotes, backslashes, controls, non-ASCII, surrogates
    direction=st.sampled_from(["tx", "rx"]),
    channel=st.sampled_from(["data", "control"]),
)
def test_a_console_line_is_encoded_exactly_as_the_general_encoder_does(
    text: str, direction: str, channel: str
) -> None:
    event = Console("laser-1.a", direction, channel, text)
    params = {"machine": event.machine, "direction": direction, "channel": channel, "text": text}
    assert console_notification(event) == encode_notification("console", params)


def test_each_notification_reaches_the_subscribers_of_the_moment() -> None:
    got: dict[str, list[bytes]] = {"a": [], "b": []}
    subs = Subscriptions()
    first = subs.add("a", got["a"].append, ["status"], None)
    subs.deliver("status", "m1", {"n": 1})
    subs.add("b", got["b"].append, ["status", "job"], "m1")
    subs.add("b", got["b"].append, ["status"], None)  # one notification a client, not two
    subs.deliver("status", "m1", {"n": 2})
    subs.deliver("status", "m2", {"n": 3})
    subs.deliver("job", "m1", {"n": 4})
    subs.remove(first)
    subs.deliver("status", "m1", {"n": 5})
    subs.remove_all("b")
    subs.deliver("status", "m1", {"n": 6})
    sent = {n: encode_notification("status" if n != 4 else "job", {"n": n}) for n in range(7)}
    assert got["a"] == [sent[1], sent[2], sent[3]]
    assert got["b"] == [sent[2], sent[3], sent[4], sent[5]]
