"""Encode what the host sends: lines, JSON GET/SET, clears, in-hold commands, realtime bytes.

Every line goes through `validate_line` first. It refuses, with a typed
`InvalidCommand`, whatever would break the board's one-answer-per-line rule
or do harm: a NUL (the board flushes its whole input), a line over 511
bytes (cut, the rest read as a new line), CR/LF inside a line (two lines,
two answers), uber-group queries and help screens (several answers), `%`
tape marks and empty lines (no answer), a leading realtime character (taken
as a control), and the bootloader commands (they can erase the firmware).
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from enum import Enum, StrEnum
from typing import Any

from hostd.protocol.relaxed import is_get, parse_relaxed

MAX_LINE_BYTES = 511


class Realtime(bytes, Enum):
    """Single-character commands: no answer, no flow-control slot, ahead of queued lines."""

    FEEDHOLD = b"!"
    CYCLE_START = b"~"
    QUEUE_FLUSH = b"%"
    JOB_KILL = b"\x04"
    RESET = b"\x18"
    ENQUIRY = b"\x05"


class Refusal(StrEnum):
    """Why a line may never be sent."""

    EMPTY = "empty"
    NUL = "nul"
    TOO_LONG = "too-long"
    LINE_BREAK = "line-break"
    CONTROL_CHAR = "control-char"
    NOT_TEXT = "not-text"
    REALTIME = "realtime"
    TAPE_MARK = "tape-mark"
    UBER_GROUP = "uber-group"
    HELP = "help"
    BOOTLOADER = "bootloader"


class InvalidCommand(ValueError):
    """The host was asked to send something the controller must never receive."""

    def __init__(self, refusal: Refusal, message: str) -> None:
        super().__init__(message)
        self.refusal = refusal
        self.message = message


_REALTIME_LEADS = frozenset(r.value.decode() for r in Realtime) - {"%"}
_UBER_GROUPS = frozenset({"m", "q", "o"})
_TEXT_UBER = frozenset({"$$", "$m", "$q", "$o"})
_HELP = frozenset({"h", "$h"})
_BOOTLOADER_KEYS = frozenset({"flash", "boot"})
_TEXT_KEY = re.compile(r"^\$([a-z0-9_]+)")
_BAD_CHAR = re.compile(r"[\x00-\x08\x0a-\x1f\x7f]")


def validate_line(line: str) -> str:
    """Return the line unchanged if it may be sent; raise InvalidCommand if not."""
    stripped = line.strip()
    if _BAD_CHAR.search(line):
        if "\x00" in line:
            raise InvalidCommand(
                Refusal.NUL, "a NUL byte makes the controller drop its whole input"
            )
        if "\n" in line or "\r" in line:
            raise InvalidCommand(Refusal.LINE_BREAK, "one command per line: CR/LF inside the line")
        if stripped[:1] not in _REALTIME_LEADS:
            raise InvalidCommand(Refusal.CONTROL_CHAR, "control characters inside the line")
    try:
        size = len(line.encode("utf-8"))
    except UnicodeEncodeError:  # a lone surrogate, as JSON's "\ud800" can carry
        raise InvalidCommand(Refusal.NOT_TEXT, "the line is not valid text") from None
    if size > MAX_LINE_BYTES:
        raise InvalidCommand(
            Refusal.TOO_LONG,
            f"line of {size} bytes: the controller cuts lines at {MAX_LINE_BYTES}",
        )
    if not stripped:
        raise InvalidCommand(Refusal.EMPTY, "an empty line gets no answer from the controller")
    lead = stripped[0]
    if lead in _REALTIME_LEADS:
        raise InvalidCommand(
            Refusal.REALTIME,
            f"a line starting with {lead!r} is a realtime command: use its own method",
        )
    if lead == "%":
        raise InvalidCommand(Refusal.TAPE_MARK, "a '%' line gets no answer from the controller")
    if lead == "{":
        obj = parse_relaxed(stripped)
        if obj is not None:
            _validate_json(obj, stripped)
    elif lead in "$Hh":
        _validate_text_command(stripped.lower())
    return line


def _validate_text_command(lowered: str) -> None:
    if lowered in _TEXT_UBER:
        raise InvalidCommand(Refusal.UBER_GROUP, f"{lowered!r} answers with several lines")
    if lowered in _HELP:
        raise InvalidCommand(Refusal.HELP, "help screens answer with several lines")
    text_key = _TEXT_KEY.match(lowered)
    if text_key and text_key.group(1) in _BOOTLOADER_KEYS:
        raise InvalidCommand(Refusal.BOOTLOADER, "bootloader commands are never sent")


def _validate_json(obj: Mapping[str, Any], line: str) -> None:
    keys = obj.keys()
    if keys & _BOOTLOADER_KEYS:
        raise InvalidCommand(Refusal.BOOTLOADER, "bootloader commands are never sent")
    if any(k in _UBER_GROUPS and is_get(obj[k]) for k in keys):
        raise InvalidCommand(Refusal.UBER_GROUP, f"{line!r} answers with several lines")


def encode_line(line: str) -> bytes:
    """A G-code or JSON line, validated and terminated."""
    return validate_line(line).encode("utf-8") + b"\n"


def _json_line(obj: Mapping[str, Any]) -> bytes:
    return encode_line(json.dumps(obj, separators=(",", ":"), allow_nan=False))


def encode_get(*keys: str) -> bytes:
    """`{"xvm":null}`: read settings (null is the board's GET form)."""
    return _json_line(dict.fromkeys(keys))


def encode_set(values: Mapping[str, Any]) -> bytes:
    """`{"xvm":16000}`: write settings; the board echoes what it stored."""
    if not values:
        raise InvalidCommand(Refusal.EMPTY, "no settings to write")
    return _json_line(values)


def encode_clear() -> bytes:
    """`{"clear":null}`: the GET form, the only one the board accepts while alarmed."""
    return encode_get("clear")


def encode_in_hold(line: str) -> bytes:
    """`{"gc2":"<line>"}`: a command run inside a feedhold, in the secondary planner."""
    validate_line(line)
    return _json_line({"gc2": line.strip()})


def encode_realtime(command: Realtime) -> bytes:
    """The single byte, then LF: the board swallows a terminator after a control character."""
    return command.value + b"\n"
