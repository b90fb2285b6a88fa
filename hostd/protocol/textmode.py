"""Read a text-mode command (`$xvm`, `$xvm=16000`, `?`, `H`) exactly as the board does, or refuse.

The board sends a line starting with `$`, `?`, `H` or `h` to its text parser
(g2core `controller.cpp`, `text_parser.cpp`):

- `?` prints a status report; any line starting with `H` prints the help
  screens. Only `?` alone is read here (`H...` is refused by the caller).
- Otherwise a leading `$` is dropped and the line lower-cased; the name runs
  to the first of ` = : | TAB` and is cut at 9 characters; whatever follows
  that first separator is read by `strtof`: if a number comes out it is a
  SET, if not the line is a GET. So `$xvm 100` is a SET and `$xvm = 100` a
  GET (the value part, `= 100`, is no number).

The host reads only the unambiguous forms and refuses the rest (UNREADABLE):
`$name` (or `hname`), a GET; `$name<sep>[spaces]<number>`, a SET, with one
separator and a plain JSON number, finite and below `numbers.BOARD_LIMIT`
(BAD_NUMBER); names of letters, digits and `_`, 9 characters at most.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from hostd.protocol.numbers import check_finite
from hostd.protocol.refusals import InvalidCommand, Refusal

TOKEN_LEN = 9  # g2core's TOKEN_LEN: longer names are silently cut
# Possessive, and read on a stripped line: linear. The lazy `\S.*?` it had, followed by
# `[ \t]*`, tried every split of a run of spaces inside the value (quadratic). The value's
# group is atomic, not `?+`: Python 3.11.2 read `$xvm=` as a read with `?+` (test_patterns.py).
_COMMAND = re.compile(r"\$?+(?P<name>[A-Za-z0-9_]++)(?>(?:[=:| \t][ \t]*+(?P<value>\S.*+))?)")
_NUMBER = re.compile(r"-?(?:0|[1-9][0-9]*)(?:\.[0-9]+)?(?:[eE][-+]?[0-9]+)?")
_INTEGER = re.compile(r"-?[0-9]+")


@dataclass(frozen=True, slots=True)
class TextCommand:
    """One text-mode line: `name` lower-cased, `value` None for a GET."""

    name: str
    value: int | float | None

    @property
    def is_get(self) -> bool:
        return self.value is None


def read_text_command(text: str) -> TextCommand:
    """The command a `$`/`h` line means; InvalidCommand if the host cannot be sure."""
    stripped = text.strip()
    m = _COMMAND.fullmatch(stripped)
    if m is None:
        raise InvalidCommand(
            Refusal.UNREADABLE,
            f"a text command the host cannot read as the board does: {stripped[:40]!r} "
            "(write $name to read a setting, $name=number to set it)",
        )
    name = m.group("name").lower()
    if len(name) > TOKEN_LEN:
        raise InvalidCommand(
            Refusal.UNREADABLE,
            f"the name {name[:20]!r} is longer than {TOKEN_LEN} characters: the board cuts it",
        )
    raw = m.group("value")
    if raw is None:
        return TextCommand(name, None)
    if not _NUMBER.fullmatch(raw):
        raise InvalidCommand(
            Refusal.UNREADABLE,
            f"the value of {name!r} is not a plain number ({raw[:20]!r}): the board would read "
            "a GET, or another number",
        )
    try:
        value: int | float = int(raw) if _INTEGER.fullmatch(raw) else float(raw)
    except ValueError:
        raise InvalidCommand(Refusal.BAD_NUMBER, f"the number of {name!r} is too long") from None
    check_finite(value, f"the value of {name!r}")
    return TextCommand(name, value)


def parse_text_command(text: str) -> TextCommand | None:
    """As `read_text_command`, but None for a line it refuses."""
    try:
        return read_text_command(text)
    except InvalidCommand:
        return None
