"""The `[mqtt]` table of the config file (docs/mqtt.md, docs/operations.md).

Absent: no MQTT. `url`, `topic_prefix` and `commands` are fixed by running.md;
the rest is the project's. The password is read from a file at start-up
(`password_file`), never written into the config itself.
"""

from __future__ import annotations

import re
import socket
from typing import Annotated
from urllib.parse import urlsplit

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

DEFAULT_PORTS = {"mqtt": 1883, "mqtts": 8883}
# Hold, resume and cancel, as the CLI's `hostd hold|resume|cancel` call them.
DEFAULT_ALLOW = ("machine.feedhold", "machine.cycle_start", "job.cancel")
# Methods that need a connection of their own to mean anything: never over MQTT.
NEVER_ALLOWED = frozenset({"subscribe", "unsubscribe"})
_METHOD = re.compile(r"^[a-z_]+(\.[a-z_]+)?$")
# A topic level of our own: no wildcards, no empty levels, no `$` at the start.
_PREFIX = re.compile(r"^[^/#+$\x00][^#+\x00]*$")


def hostname() -> str:
    """This host's short name, as MQTT topic levels and client ids want it."""
    name = socket.gethostname().split(".")[0] or "localhost"
    return re.sub(r"[^A-Za-z0-9_-]", "-", name)


class MqttConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    # mqtt://host[:port] or mqtts://host[:port] (TLS; the system's CAs unless ca_file).
    url: str
    # The client id the broker knows this daemon by; default hostd-<hostname>.
    client_id: Annotated[str, Field(min_length=1, max_length=128)] | None = None
    # Every topic starts with it; default hostd/<hostname>.
    topic_prefix: str | None = None
    username: str | None = None
    # A file holding the password (its first line); read at start-up.
    password_file: str | None = None
    # TLS (mqtts://): a CA bundle to trust instead of the system's, a client
    # certificate and key, and `tls_insecure` to skip the host name check.
    ca_file: str | None = None
    cert_file: str | None = None
    key_file: str | None = None
    tls_insecure: bool = False
    # Accept requests on <prefix>/<machine>/cmd/<method>; only methods in `allow`.
    commands: bool = False
    allow: list[str] = list(DEFAULT_ALLOW)
    # Seconds between two publications of one machine's status (or job) topic at most.
    status_interval: Annotated[float, Field(ge=0.05, le=60)] = 0.25
    # Home Assistant MQTT discovery under `discovery_prefix`.
    homeassistant: bool = False
    discovery_prefix: str = "homeassistant"
    # Reconnect back-off, seconds: from reconnect_min, doubling, up to reconnect_max.
    reconnect_min: Annotated[float, Field(gt=0, le=60)] = 1.0
    reconnect_max: Annotated[float, Field(gt=0, le=3600)] = 60.0
    keepalive: Annotated[int, Field(ge=5, le=3600)] = 30
    # Seconds a publication may take before the broker is taken for gone (reconnect).
    publish_timeout: Annotated[float, Field(gt=0, le=600)] = 10.0
    # Events (exceptions, command replies) kept while the broker is away; the oldest go first.
    max_events: Annotated[int, Field(ge=1, le=100_000)] = 100
    # Seconds a command may take from its `sent_at` to the daemon; older is refused (a
    # command queued by a broker through an outage must not move a machine minutes later).
    command_max_age: Annotated[float, Field(gt=0, le=3600)] = 30.0
    # Commands a second the bridge takes, with bursts of `command_burst`; past it each is
    # refused with a published error (-32000) and a log line.
    command_rate: Annotated[float, Field(gt=0, le=10_000)] = 5.0
    command_burst: Annotated[int, Field(ge=1, le=10_000)] = 20
    # Bytes of a command's payload; larger is refused unread. The broker is told our
    # maximum packet size (this plus room for the topic and properties): it never sends
    # us anything bigger.
    max_payload: Annotated[int, Field(ge=1024, le=16 << 20)] = 65536

    @field_validator("url")
    @classmethod
    def _url(cls, url: str) -> str:
        parts = urlsplit(url)
        if parts.scheme not in DEFAULT_PORTS:
            raise ValueError('must start with "mqtt://" or "mqtts://"')
        if not parts.hostname:
            raise ValueError("names no host")
        try:
            parts.port  # noqa: B018 (raises on a bad port)
        except ValueError:
            raise ValueError("has a bad port") from None
        if parts.path not in ("", "/") or parts.query or parts.username:
            raise ValueError("only mqtt[s]://host[:port]: user and password are keys of their own")
        return url

    @field_validator("topic_prefix", "discovery_prefix")
    @classmethod
    def _prefix(cls, prefix: str | None) -> str | None:
        if prefix is None:
            return None
        if not _PREFIX.match(prefix) or prefix.endswith("/") or "//" in prefix:
            raise ValueError("a topic without wildcards (+ #), empty levels or a leading $ or /")
        return prefix

    @field_validator("allow")
    @classmethod
    def _methods(cls, allow: list[str]) -> list[str]:
        for name in allow:
            if not _METHOD.match(name):
                raise ValueError(f"{name!r} is not a method name")
            if name in NEVER_ALLOWED:
                raise ValueError(f"{name!r} cannot be called over MQTT")
        return allow

    @model_validator(mode="after")
    def _tls_only_with_mqtts(self) -> MqttConfig:
        tls = self.ca_file or self.cert_file or self.key_file or self.tls_insecure
        if tls and not self.tls:
            raise ValueError("ca_file, cert_file, key_file and tls_insecure need an mqtts:// url")
        if self.key_file and not self.cert_file:
            raise ValueError("key_file needs cert_file")
        if self.reconnect_max < self.reconnect_min:
            raise ValueError("reconnect_max is below reconnect_min")
        return self

    @property
    def tls(self) -> bool:
        return urlsplit(self.url).scheme == "mqtts"

    @property
    def host(self) -> str:
        return urlsplit(self.url).hostname or ""

    @property
    def port(self) -> int:
        parts = urlsplit(self.url)
        return parts.port or DEFAULT_PORTS[parts.scheme]

    @property
    def prefix(self) -> str:
        return self.topic_prefix or f"hostd/{hostname()}"

    @property
    def identifier(self) -> str:
        return self.client_id or f"hostd-{hostname()}"


def read_password(config: MqttConfig) -> str | None:
    """The password's first line, or None without a password file. Raises OSError."""
    if config.password_file is None:
        return None
    with open(config.password_file, encoding="utf-8") as f:
        return f.readline().rstrip("\r\n")
