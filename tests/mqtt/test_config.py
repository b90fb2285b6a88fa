"""The [mqtt] table, topic names and payload slicing."""

from __future__ import annotations

import json
from typing import Any

import jinja2
import pytest

from hostd.api.mqtt import topics
from hostd.api.mqtt.config import DEFAULT_ALLOW, hostname
from hostd.api.rpc import encode_notification
from hostd.config import ConfigError, parse_config


def config(**mqtt: Any) -> Any:
    return parse_config({"mqtt": {"url": "mqtt://broker.lan", **mqtt}}).mqtt


def test_defaults() -> None:
    mqtt = config()
    assert (mqtt.host, mqtt.port, mqtt.tls) == ("broker.lan", 1883, False)
    assert mqtt.prefix == f"hostd/{hostname()}"
    assert mqtt.identifier == f"hostd-{hostname()}"
    assert mqtt.commands is False
    assert tuple(mqtt.allow) == DEFAULT_ALLOW
    assert parse_config({}).mqtt is None


def test_mqtts_defaults_to_8883() -> None:
    mqtt = config(url="mqtts://broker.lan", ca_file="/etc/ssl/ca.pem")
    assert (mqtt.port, mqtt.tls) == (8883, True)


@pytest.mark.parametrize(
    ("mqtt", "problem"),
    [
        ({"url": "http://broker"}, "mqtt://"),
        ({"url": "mqtt://"}, "no host"),
        ({"url": "mqtt://u:p@broker"}, "user and password"),
        ({"topic_prefix": "a/+/b"}, "wildcards"),
        ({"topic_prefix": "a/"}, "wildcards"),
        ({"allow": ["subscribe"]}, "cannot be called"),
        ({"ca_file": "/ca.pem"}, "mqtts://"),
        ({"colour": "red"}, "unknown key"),
    ],
)
def test_bad_tables_name_the_key(mqtt: dict[str, Any], problem: str) -> None:
    with pytest.raises(ConfigError, match=problem):
        config(**mqtt)


def test_params_are_sliced_from_the_notification_as_encoded() -> None:
    params = {"machine": "m1", "report": {"stat": 5, "text": 'a "quoted" é'}}
    line = encode_notification("status", params)
    assert json.loads(topics.params_of(line)) == params
    assert topics.params_of(line) == line[line.index(b'"params":') + 9 : -1]


@pytest.mark.parametrize(
    ("topic", "parsed"),
    [
        ("p/q/m1/cmd/job.cancel", ("m1", "job.cancel")),
        ("p/q/m1/cmd/", None),
        ("p/q/m1/status", None),
        ("other/m1/cmd/job.cancel", None),
    ],
)
def test_command_topics(topic: str, parsed: tuple[str, str] | None) -> None:
    assert topics.parse_command("p/q", topic) == parsed


def test_home_assistant_discovery_names_every_entity_once() -> None:
    found = topics.discovery("homeassistant", "hostd/shop", "laser1", "g2core")
    names = [topic for topic, _ in found]
    assert len(set(names)) == len(names) == 6
    for topic, payload in found:
        entity = json.loads(payload)
        assert topic.startswith("homeassistant/") and topic.endswith("/config")
        assert entity["availability_topic"] == "hostd/shop/online"
        assert entity["state_topic"].startswith("hostd/shop/laser1/")


@pytest.mark.parametrize(
    ("snapshot", "problem", "lockout"),
    [
        ({"indicator": "normal", "lockout": None}, "OFF", "none"),
        ({"indicator": "alert", "lockout": None}, "ON", "none"),
        (
            {
                "indicator": "normal",
                "lockout": {"state": "ALARM", "message": "Limit hit", "clear": "machine.clear"},
            },
            "ON",
            "ALARM: Limit hit",
        ),
        (  # connecting to a grbl board busy with moves of before (docs/dialects.md)
            {
                "indicator": "normal",
                "lockout": None,
                "occupied": {"state": "Hold", "message": "m1 is Hold, busy with moves"},
            },
            "ON",
            "connecting, Hold: m1 is Hold, busy with moves",
        ),
        ({"indicator": "normal", "lockout": None, "occupied": None}, "OFF", "none"),
    ],
)
def test_home_assistant_shows_a_controller_lockout_as_a_problem(
    snapshot: dict[str, object], problem: str, lockout: str
) -> None:
    """The templates rendered with Jinja2, as Home Assistant renders them."""
    found = dict(topics.discovery("homeassistant", "hostd/shop", "laser1", "g2core"))
    entities = {topic.split("/")[-2]: json.loads(payload) for topic, payload in found.items()}
    seen = {"value_json": {"snapshot": snapshot}}
    env = jinja2.Environment(undefined=jinja2.StrictUndefined)
    assert env.from_string(entities["fault"]["value_template"]).render(seen) == problem
    assert env.from_string(entities["lockout"]["value_template"]).render(seen) == lockout
    # Its attributes: the lockout as the snapshot has it, with what ends it; none outside one.
    attributes = env.from_string(entities["lockout"]["json_attributes_template"]).render(seen)
    assert json.loads(attributes) == (snapshot["lockout"] or {})
