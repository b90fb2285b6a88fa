"""Encode what the host sends: lines, JSON GET/SET, clears, in-hold commands, realtime bytes.

Every line goes through `validate_line` first. It refuses, with a typed
`InvalidCommand`, whatever would break the board's one-answer-per-line rule
or do harm: a NUL (the board flushes its whole input), a line over 511
bytes (cut, the rest read as a new line), CR/LF inside a line (two lines,
two answers), uber-group queries and help screens (several answers), `%`
tape marks and empty lines (no answer), a leading realtime character (taken
as a control), and the bootloader commands (they can erase the firmware).

The rule above all: the host sends only what it reads exactly as the board
will, since that reading is what classifies the line (classes.py). A JSON
line is read by `relaxed.read_relaxed` (names twice, nesting the board
misreads, escapes, out-of-range numbers: refused), a text command by
`textmode.read_text_command`, a G-code line checked by `gcode.check_gcode`
(words the board would misread, active comments). A line none of them can
read is refused, never sent as a guess. A client's line may also not SET a
value the daemon owns (`settings.DAEMON_OWNED`: `{jv:0}` would silence the
board); the daemon's own lines (`encode_set`) may.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from enum import Enum
from typing import Any

from hostd.protocol.gcode import check_gcode, is_plain
from hostd.protocol.refusals import InvalidCommand as InvalidCommand
from hostd.protocol.refusals import Refusal as Refusal
from hostd.protocol.relaxed import board_pairs, is_get, read_relaxed
from hostd.protocol.settings import DAEMON_OWNED, RESERVED
from hostd.protocol.textmode import read_text_command

MAX_LINE_BYTES = 511


class Realtime(bytes, Enum):
    """Single-character commands: no answer, no flow-control slot, ahead of queued lines."""

    FEEDHOLD = b"!"
    CYCLE_START = b"~"
    QUEUE_FLUSH = b"%"
    JOB_KILL = b"\x04"
    RESET = b"\x18"
    ENQUIRY = b"\x05"


_REALTIME_LEADS = frozenset(r.value.decode() for r in Realtime) - {"%"}
_UBER_GROUPS = frozenset({"m", "q", "o"})
_TEXT_UBER = frozenset({"$$", "$m", "$q", "$o"})
_HELP_KEYS = frozenset({"h", "help", "defa"})  # a GET of these prints help screens
_BOOTLOADER_KEYS = frozenset({"flash", "boot"})
_GCODE_KEYS = frozenset({"gc", "gc2"})
_TEXT_LEADS = "$?Hh"  # a line starting so is a text-mode command, not G-code
_BAD_CHAR = re.compile(r"[\x00-\x08\x0a-\x1f\x7f]")


def validate_line(line: str) -> str:
    """Return a client's (or a job's) line unchanged if it may be sent; else InvalidCommand."""
    _validate(line, client=True)
    return line


def _validate(line: str, *, client: bool) -> None:
    stripped = _check_frame(line)
    lead = stripped[0]
    if lead == "{":
        _validate_json(stripped, client=client)
    elif lead in _TEXT_LEADS:
        _validate_text_command(stripped, client=client)
    else:
        check_gcode(stripped)


def _check_frame(line: str) -> str:
    """The rules on bytes and the first character; the stripped line."""
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
    return stripped


def _validate_text_command(stripped: str, *, client: bool) -> None:
    if stripped.lower() in _TEXT_UBER:
        raise InvalidCommand(Refusal.UBER_GROUP, f"{stripped!r} answers with several lines")
    if stripped[0] == "H":
        raise InvalidCommand(Refusal.HELP, "a line starting with 'H' prints the help screens")
    if stripped[0] == "?":
        if stripped != "?":
            raise InvalidCommand(Refusal.UNREADABLE, "'?' is a status request only on its own")
        return
    command = read_text_command(stripped)
    _check_names((command.name,), command.value, client=client)


def _validate_json(text: str, *, client: bool) -> None:
    for names, value in board_pairs(read_relaxed(text)):
        _check_names(names, value, client=client)
        if _GCODE_KEYS & set(names) and not is_get(value):
            if not isinstance(value, str):
                raise InvalidCommand(Refusal.UNREADABLE, f"{names[0]!r} takes a G-code string")
            check_gcode(value)


def _check_names(names: tuple[str, ...], value: object, *, client: bool) -> None:
    """One pair (JSON) or one text command, by every name the board may look it up by."""
    named = set(names)
    get = is_get(value)
    if named & _BOOTLOADER_KEYS:
        raise InvalidCommand(Refusal.BOOTLOADER, "bootloader commands are never sent")
    if get and named & _UBER_GROUPS:
        raise InvalidCommand(Refusal.UBER_GROUP, f"{names[0]!r} answers with several lines")
    if get and named & _HELP_KEYS:
        raise InvalidCommand(Refusal.HELP, "help screens answer with several lines")
    owned = named & DAEMON_OWNED
    if client and not get and owned:
        name = min(owned)
        raise InvalidCommand(
            Refusal.RESERVED_KEY, f"{name!r} is the daemon's to set: {RESERVED[name].reason}"
        )


def encode_line(line: str) -> bytes:
    """A G-code or JSON line, validated and terminated."""
    if len(line) <= MAX_LINE_BYTES and line[:1] not in _TEXT_LEADS and is_plain(line):
        # A job's every line: plain G-code words (ASCII letters, digits, signs, points
        # and blanks), which every rule of `_validate` lets through. One match, not ten.
        return line.encode("ascii") + b"\n"
    return validate_line(line).encode("utf-8") + b"\n"


def _json_line(obj: Mapping[str, Any]) -> bytes:
    """One of the daemon's own JSON lines: every rule but DAEMON_OWNED applies."""
    text = json.dumps(obj, separators=(",", ":"), allow_nan=False, ensure_ascii=False)
    _validate(text, client=False)
    return text.encode("utf-8") + b"\n"


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
    """`{"gc2":"<line>"}`: a command run inside a feedhold, in the secondary planner.

    The board's strings have no escapes: a line with a quote or a backslash
    cannot be wrapped (it would end the string early), and a TAB is sent as
    the space the board reads it as.
    """
    validate_line(line)
    text = line.strip().replace("\t", " ")
    if '"' in text or "\\" in text:
        raise InvalidCommand(
            Refusal.UNREADABLE,
            "a line sent during a hold is wrapped in a JSON string, which cannot hold "
            "a quote or a backslash on this board",
        )
    return _json_line({"gc2": text})


def encode_realtime(command: Realtime) -> bytes:
    """The single byte, then LF: the board swallows a terminator after a control character."""
    return command.value + b"\n"
