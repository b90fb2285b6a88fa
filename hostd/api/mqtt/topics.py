"""Topic names, payloads and Home Assistant discovery: pure functions, no I/O.

Payloads are the `params` of the API's notifications (api.md, Subscriptions),
byte for byte: a dashboard reads `value_json.snapshot.state.name` from
`<prefix>/<machine>/status` as a socket client reads `params.snapshot.state.name`.
The one payload of our own is `faults` (a retained topic needs the whole
table, not the last change): `{"machine", "faults": [fault object, ...]}`, as
`fault.list` answers.
"""

from __future__ import annotations

import json
import re
from typing import Any

ONLINE = b"online"
OFFLINE = b"offline"
RETAINED_TOPICS = ("status", "job", "faults")
EVENT_TOPICS = ("exception",)

_NOTIFICATION_HEAD = b'{"jsonrpc":"2.0","method":"'
_PARAMS_KEY = b'","params":'


# A response topic is under `<prefix>/replies/`: never one of our own topics (a reply on
# `<prefix>/<machine>/cmd/...` would be a command to ourselves), never a wildcard.
REPLIES = "replies"
MAX_TOPIC = 1024  # bytes of a response topic


def online(prefix: str) -> str:
    return f"{prefix}/online"


def errors(prefix: str) -> str:
    """Refusals that have nowhere else to go (no usable response topic): an event topic."""
    return f"{prefix}/errors"


def response_topic_problem(prefix: str, topic: str) -> str | None:
    """Why `topic` cannot be a response topic, or None when it can.

    Checked before anything is published to it: a wildcard is not a topic one may
    publish to (the client library raises), and a topic outside `<prefix>/replies/`
    could be one of ours (a status, a command) or anyone's.
    """
    head = f"{prefix}/{REPLIES}/"
    if "+" in topic or "#" in topic or "\x00" in topic:
        return "response topic has a wildcard (+ #) or NUL"
    if len(topic.encode("utf-8", "surrogatepass")) > MAX_TOPIC:
        return f"response topic over {MAX_TOPIC} bytes"
    if not topic.startswith(head) or len(topic) == len(head) or "//" in topic[len(head) - 1 :]:
        return f"response topic must be under {head}"
    return None


def machine_topic(prefix: str, machine: str, name: str) -> str:
    return f"{prefix}/{machine}/{name}"


def command_filter(prefix: str) -> str:
    """What the bridge subscribes to when commands are on."""
    return f"{prefix}/+/cmd/+"


def parse_command(prefix: str, topic: str) -> tuple[str, str] | None:
    """(machine, method) of a command topic, or None when it is not one of ours."""
    head = prefix + "/"
    if not topic.startswith(head):
        return None
    parts = topic[len(head) :].split("/")
    if len(parts) != 3 or parts[1] != "cmd" or not parts[0] or not parts[2]:
        return None
    return parts[0], parts[2]


def params_of(notification: bytes) -> bytes:
    """The `params` of an encoded notification (rpc.encode_notification), as bytes.

    The encoder writes `{"jsonrpc":"2.0","method":"<name>","params":<params>}`
    compactly, always in that order: the params are a slice of it, with no
    decoding and re-encoding of a whole snapshot. Anything else is parsed.
    """
    if notification.startswith(_NOTIFICATION_HEAD) and notification.endswith(b"}"):
        at = notification.find(_PARAMS_KEY, len(_NOTIFICATION_HEAD))
        if at != -1 and b'"' not in notification[len(_NOTIFICATION_HEAD) : at]:
            return notification[at + len(_PARAMS_KEY) : -1]
    params = json.loads(notification).get("params")
    return json.dumps(params, separators=(",", ":"), ensure_ascii=False).encode()


def encode(value: Any) -> bytes:
    return json.dumps(value, separators=(",", ":"), ensure_ascii=False, allow_nan=False).encode()


# --- Home Assistant discovery ------------------------------------------------


def _object_id(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_-]", "_", text)


def discovery(
    discovery_prefix: str, prefix: str, machine: str, dialect: str
) -> list[tuple[str, bytes]]:
    """Retained discovery messages for one machine: (topic, payload).

    The machine is one device with its state, supervisor, job state, job
    progress and lockout (ALARM, SHUTDOWN, PANIC, INTERLOCK, why, and what ends it) as sensors,
    and its fault indicator or a lockout as a `problem` binary sensor;
    all of them unavailable while the daemon's `online` topic says `offline`.
    """
    node = _object_id(prefix)
    uid = f"{node}_{_object_id(machine)}"
    status = machine_topic(prefix, machine, "status")
    job = machine_topic(prefix, machine, "job")
    common: dict[str, Any] = {
        "availability_topic": online(prefix),
        "payload_available": ONLINE.decode(),
        "payload_not_available": OFFLINE.decode(),
        "device": {
            "identifiers": [uid],
            "name": machine,
            "manufacturer": "hostd",
            "model": dialect,
        },
    }
    entities: list[tuple[str, str, dict[str, Any]]] = [
        (
            "sensor",
            "state",
            {
                "name": "State",
                "state_topic": status,
                "value_template": "{{ value_json.snapshot.state.name }}",
            },
        ),
        (
            "sensor",
            "supervisor",
            {
                "name": "Supervisor",
                "state_topic": status,
                "value_template": "{{ value_json.snapshot.supervisor }}",
            },
        ),
        (
            "sensor",
            "job_state",
            {
                "name": "Job",
                "state_topic": job,
                "value_template": "{{ value_json.job.state }}",
                "json_attributes_topic": job,
                "json_attributes_template": "{{ value_json.job | tojson }}",
            },
        ),
        (
            "sensor",
            "job_progress",
            {
                "name": "Job progress",
                "state_topic": job,
                "unit_of_measurement": "%",
                "value_template": (
                    "{% set j = value_json.job %}"
                    "{{ (100 * j.lines_acked / j.lines_total) | round(1)"
                    " if j.lines_total else 0 }}"
                ),
            },
        ),
        (
            "binary_sensor",
            "fault",
            {
                "name": "Fault",
                "device_class": "problem",
                "state_topic": status,
                # A controller lockout is a problem too, whatever the fault table says, and
                # so is a board found busy with moves of before while connecting.
                "value_template": (
                    "{{ 'ON' if value_json.snapshot.indicator == 'alert'"
                    " or value_json.snapshot.lockout"
                    " or value_json.snapshot.get('occupied') else 'OFF' }}"
                ),
            },
        ),
        (
            "sensor",
            "lockout",
            {
                "name": "Lockout",
                "icon": "mdi:alert-octagon",
                "state_topic": status,
                "value_template": (
                    "{% set l = value_json.snapshot.lockout %}"
                    "{% set o = value_json.snapshot.get('occupied') %}"
                    "{{ l.state ~ ': ' ~ l.message if l"
                    " else 'connecting, ' ~ o.state ~ ': ' ~ o.message if o else 'none' }}"
                ),
                # Its state, reason and what ends it (`clear`), as the dashboard shows them.
                "json_attributes_topic": status,
                "json_attributes_template": "{{ (value_json.snapshot.lockout or {}) | tojson }}",
            },
        ),
    ]
    out = []
    for component, key, entity in entities:
        config = {**entity, **common, "unique_id": f"{uid}_{key}", "object_id": f"{uid}_{key}"}
        out.append((f"{discovery_prefix}/{component}/{uid}/{key}/config", encode(config)))
    return out
