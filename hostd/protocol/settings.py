"""Which names `settings.set` and `settings.get` refuse, and how setting values are written.

Everything that decides "is this name a setting a client may write?" is the
one table below, `RESERVED`, with the reason given to the client. The names
come from g2core's configuration table (`config_app.cpp`,
`canonical_machine.cpp`) and `../shared/spec/g2core.md`. Each entry says
where it is refused:

- `settings.set`: always (none of these is a setting a client writes).
- `settings.get` too, when even a GET of the name acts (`{clear:n}` clears,
  `{alarm:n}` raises an alarm, `{defa:n}` prints a help screen).
- `machine.send` too, as a SET in any form (`{jv:0}`, `$jv=0`, a nested
  `{sys:{jv:0}}`), when the daemon itself owns the value: the link settings it
  sends after every connect and the status report list it reads the machine
  by. `machine.send` still sends G-code (`gc`), clears and alarms: those
  have their own rules (classes.py).

Values: numbers as `numbers.format_setting` writes them (finite, below
`numbers.BOARD_LIMIT`, six decimals at most, no exponent); booleans as
`true`/`false`; text of printable ASCII without spaces, quotes, backslashes
or parentheses (the board drops spaces, ends a string at the next quote,
has no escapes, and reads parentheses as a G-code comment), at most
`MAX_TEXT` characters. The board stores text lower-cased.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from dataclasses import dataclass
from enum import Flag, auto

from hostd.protocol.numbers import format_setting
from hostd.protocol.refusals import InvalidCommand, Refusal

MAX_TEXT = 100
_TEXT = re.compile(r"[!#-'*-\[\]-~]+")  # printable ASCII but space, `"`, `(`, `)` and `\`


class Where(Flag):
    """Where a reserved name is refused, beyond `settings.set`."""

    SET = auto()  # settings.set
    GET = auto()  # settings.get: a GET of it acts
    SEND = auto()  # a SET of it through machine.send: the daemon owns the value


@dataclass(frozen=True, slots=True)
class Reserved:
    reason: str
    where: Where = Where.SET


_LINK = Where.SET | Where.SEND
_ACTS = Where.SET | Where.GET
_ALL = Where.SET | Where.GET | Where.SEND

RESERVED: dict[str, Reserved] = {
    # G-code travels as lines, counted and classified one by one.
    "gc": Reserved("G-code, not a setting: send it with machine.send or a job"),
    "gc2": Reserved("G-code for the in-hold planner, not a setting: use machine.send"),
    # The link the daemon sets up after every connect (g2core.md, section 10).
    "ej": Reserved("the daemon keeps the board in JSON mode; text mode breaks the link", _LINK),
    "jv": Reserved("the daemon's JSON verbosity: at 0 or 6 the board stops answering", _LINK),
    "sv": Reserved("the daemon's status report verbosity: it reads the machine by them", _LINK),
    "si": Reserved("the daemon's status report interval (the machine's status_interval)", _LINK),
    "qv": Reserved("the daemon's queue report verbosity", _LINK),
    "tv": Reserved("the daemon's text verbosity", _LINK),
    "sr": Reserved("the daemon owns the status report list (its GET is a status report)", _LINK),
    "defa": Reserved(
        "restores the factory defaults, the daemon's link settings with them; "
        "its GET prints a help screen",
        _ALL,
    ),
    # Firmware (also refused in every form by validate_line).
    "boot": Reserved("the bootloader: on some boards it erases the firmware", _ALL),
    "flash": Reserved("the bootloader: on some boards it erases the firmware", _ALL),
    # Commands, not settings: each has its method, or none on purpose.
    "clear": Reserved("clears an alarm or shutdown (even as a GET): use machine.clear", _ACTS),
    "clr": Reserved("clears an alarm or shutdown (even as a GET): use machine.clear", _ACTS),
    "alarm": Reserved("raises an alarm (even as a GET): use machine.alarm", _ACTS),
    "shutd": Reserved("raises a shutdown (even as a GET): use machine.shutdown", _ACTS),
    "panic": Reserved("raises a panic (even as a GET); only a reset leaves it", _ACTS),
    "estp": Reserved("acknowledges an emergency stop: not a setting"),
    "estpc": Reserved("acknowledges an emergency stop (even as a GET): not a setting", _ACTS),
    "me": Reserved("energises the motors: an action, not a setting"),
    "md": Reserved("de-energises the motors: an action, not a setting"),
    "tram": Reserved("computes a rotation from probed points: an action, not a setting"),
    "clc": Reserved("clears the step counters (even as a GET): an action", _ACTS),
    "er": Reserved("its GET raises a test exception report", _ACTS),
    "help": Reserved("prints help screens: several answers to one line", _ACTS),
    "h": Reserved("prints help screens: several answers to one line", _ACTS),
    # The status report list as the board persists it, one slot a name.
    **{
        f"se{slot:02d}": Reserved("a slot of the status report list, which the daemon owns", _LINK)
        for slot in range(39)
    },
}

# Names whose SET machine.send refuses: the daemon owns their values.
DAEMON_OWNED = frozenset(name for name, r in RESERVED.items() if Where.SEND in r.where)


def check_key(key: str, *, read: bool = False) -> None:
    """Refuse a name `settings.set` (or, with `read`, `settings.get`) must not send."""
    name = key.lower()
    reserved = RESERVED.get(name)
    if reserved is None or (read and Where.GET not in reserved.where):
        return
    raise InvalidCommand(
        Refusal.RESERVED_KEY, f"{name!r} is not a setting to change here: {reserved.reason}"
    )


def value_text(key: str, value: bool | int | float | str) -> str:
    """The value as it goes on the line, or InvalidCommand (BAD_NUMBER, BAD_VALUE)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return format_setting(value, f"the value of {key!r}")
    if len(value) > MAX_TEXT or not _TEXT.fullmatch(value):
        raise InvalidCommand(
            Refusal.BAD_VALUE,
            f"the value of {key!r} must be 1 to {MAX_TEXT} printable ASCII characters "
            "without spaces, quotes, backslashes or parentheses: the board would read "
            "another value (and an empty string as a GET)",
        )
    return json.dumps(value)


def check_values(values: Mapping[str, bool | int | float | str]) -> None:
    """Refuse reserved names, names given twice (case-insensitively) and bad values."""
    seen: dict[str, str] = {}
    for key, value in values.items():
        check_key(key)
        name = key.lower()
        if name in seen:
            raise InvalidCommand(
                Refusal.DUPLICATE_KEY,
                f"{seen[name]!r} and {key!r} name the same setting (the board ignores case)",
            )
        seen[name] = key
        value_text(key, value)


def set_lines(values: Mapping[str, bool | int | float | str]) -> list[str]:
    """One SET line a setting, in order: the board answers each with the value it stored."""
    check_values(values)
    return [f'{{"{key.lower()}":{value_text(key, value)}}}' for key, value in values.items()]
