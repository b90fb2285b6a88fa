"""The API's fan-out: one encoding for every subscriber, the right subscribers after any change."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from hostd.api.methods import Subscriptions, console_notification
from hostd.api.methods.subscriptions import JOB_LINES
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


def test_a_jobs_console_lines_go_only_where_they_were_not_left_out() -> None:
    got: dict[str, list[bytes]] = {"full": [], "lean": [], "both": []}
    subs = Subscriptions()
    subs.add("full", got["full"].append, ["console"], None)
    subs.add("lean", got["lean"].append, ["console", "status"], None, job_lines=False)
    # One client, two subscriptions: without the job's lines everywhere, with them on m1.
    subs.add("both", got["both"].append, ["console"], None, job_lines=False)
    subs.add("both", got["both"].append, ["console"], "m1")
    assert subs.wants(JOB_LINES, "m2") and subs.wants("console", "m2")
    events = [
        Console("m1", "tx", "data", "N7 G1 X1", job=True),
        Console("m1", "rx", "data", "ok", job=True),
        Console("m1", "tx", "data", "$G"),
        Console("m2", "tx", "data", "N9 G1 X2", job=True),
        Console("m2", "rx", "data", "error:20"),
    ]
    for event in events:
        key = JOB_LINES if event.job else "console"
        subs.deliver_line(key, event.machine, console_notification(event))
    line = {e.text: console_notification(e) for e in events}
    assert got["full"] == [console_notification(e) for e in events]
    assert got["lean"] == [line["$G"], line["error:20"]]
    assert got["both"] == [line["N7 G1 X1"], line["ok"], line["$G"], line["error:20"]]
    subs.remove_all("full")
    subs.remove_all("both")
    assert not subs.wants(JOB_LINES, "m1") and subs.wants("console", "m1")
