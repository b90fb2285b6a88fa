"""Typed messages: one for every kind of line a g2core board can send.

The parser turns each line into exactly one of these; nothing else crosses
from the wire into the rest of the daemon. Every message keeps the raw bytes
it came from, for the console stream and for diagnostics.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

JsonObject = dict[str, Any]


@dataclass(frozen=True, slots=True)
class Response:
    """`{"r":{...},"f":[rev,status,count]}`: the one answer to one host line."""

    body: JsonObject
    status: int
    count: int
    raw: bytes

    @property
    def ok(self) -> bool:
        return self.status == 0

    @property
    def status_report(self) -> JsonObject | None:
        """The fields of a requested status report (`{sr:n}` or `?`), if this is one."""
        sr = self.body.get("sr")
        return sr if isinstance(sr, dict) else None


@dataclass(frozen=True, slots=True)
class Banner:
    """The SYSTEM READY line sent on every open. It is an `{r}`, but answers no host line."""

    fv: float | None
    fb: float | None
    hp: str | int | None
    hv: str | int | None
    id: str | None
    body: JsonObject
    raw: bytes

    @property
    def is_tinyg(self) -> bool:
        """TinyG builds are 400 and up; their status codes differ from g2core's."""
        return self.fb is not None and self.fb >= 400


@dataclass(frozen=True, slots=True)
class StatusReport:
    """An automatic `{"sr":{...}}`: only the keys that changed (filtered mode)."""

    fields: JsonObject
    raw: bytes


@dataclass(frozen=True, slots=True)
class ExceptionReport:
    """`{"er":{"fb":..,"st":..,"msg":..}}`: alarms, shutdowns, panics, job kill."""

    status: int | None
    message: str
    fields: JsonObject
    raw: bytes


@dataclass(frozen=True, slots=True)
class QueueReport:
    """`{"qr":n}` or `{"qr":n,"qi":a,"qo":b}`: free planner buffers."""

    qr: int
    qi: int | None
    qo: int | None
    raw: bytes


@dataclass(frozen=True, slots=True)
class Ack:
    """`{"ack":true}`, the answer to ENQ (0x05)."""

    raw: bytes


@dataclass(frozen=True, slots=True)
class Notice:
    """A well-formed JSON object of no kind above, e.g. `{"muted":true}`."""

    fields: JsonObject
    raw: bytes


@dataclass(frozen=True, slots=True)
class TextLine:
    """A printable non-JSON line: text-mode prompts, help screens."""

    text: str
    raw: bytes


@dataclass(frozen=True, slots=True)
class Unparseable:
    """Bytes that are no valid line: noise, invalid UTF-8, broken JSON, a missing footer."""

    reason: str
    raw: bytes


Message = (
    Response
    | Banner
    | StatusReport
    | ExceptionReport
    | QueueReport
    | Ack
    | Notice
    | TextLine
    | Unparseable
)
