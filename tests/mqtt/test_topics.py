"""Which response topics the bridge publishes an answer to (docs/mqtt.md): only a
plain topic under `<prefix>/replies/`, of at most 1024 bytes. Anything else would be a
topic of ours (a status, a command), someone else's, or one no client may publish to."""

from __future__ import annotations

import pytest

from hostd.api.mqtt.topics import MAX_TOPIC, response_topic_problem

PREFIX = "shop/h1"
HEAD = f"{PREFIX}/replies/"


@pytest.mark.parametrize(
    "topic",
    [
        f"{HEAD}a",
        f"{HEAD}4711/7f3a",  # a client's own levels under its reply topic
        HEAD + "é" * ((MAX_TOPIC - len(HEAD)) // 2),  # at the limit in bytes, not characters
    ],
)
def test_a_topic_under_the_replies_is_answered(topic: str) -> None:
    assert response_topic_problem(PREFIX, topic) is None


@pytest.mark.parametrize(
    ("topic", "why"),
    [
        (HEAD, "must be under"),  # the replies level itself: nobody's own topic
        (f"{PREFIX}/replies", "must be under"),
        (f"{PREFIX}/repliesx/a", "must be under"),  # a longer level that starts the same
        (f"{HEAD}/a", "must be under"),  # an empty level: another topic than it seems
        (f"{HEAD}a//b", "must be under"),
        ("other/h1/replies/a", "must be under"),
        (f"{PREFIX}/sim1/status", "must be under"),
        (f"{HEAD}a/+", "wildcard"),
        (f"{HEAD}#", "wildcard"),
        (f"{HEAD}a\x00b", "NUL"),
        (HEAD + "é" * ((MAX_TOPIC - len(HEAD)) // 2 + 1), f"over {MAX_TOPIC} bytes"),
    ],
)
def test_any_other_topic_is_refused_with_its_reason(topic: str, why: str) -> None:
    problem = response_topic_problem(PREFIX, topic)
    assert problem is not None and why in problem
