"""Read g2core's relaxed JSON input exactly as the board does, or refuse to.

The board accepts `{xvm:n}`, `{clear:n}`, `{sr:{posx:t}}`: unquoted keys,
`n` for null (a GET), `t`/`f` for true/false. The daemon must understand a
client's line exactly as the board will, to classify it before sending; a
line it cannot read with certainty is refused, never sent on a guess.

What the board does (g2core `json_parser.cpp`), and what that makes the host
refuse (`InvalidCommand`, refusal UNREADABLE unless said otherwise):

- It lower-cases the whole line and drops every space: names are
  case-insensitive. It reads the pairs into a list and runs them *in order*,
  so a name given twice runs twice (`{gc:"G0 X100",clear:n,gc:n}` moves,
  then clears). Any name twice, whatever its case, is DUPLICATE_KEY.
- It reads two levels and does not track closing braces: once it has read a
  nested object, every later pair is taken as one of its members, looked up
  under the group's prefix (`{x:{vm:1},am:n}` reads `xam`). An object may
  only be the last pair, and holds only plain values. As `{x:{vm:1}}` sets
  `xvm`, a member is known by both names (`vm` and `xvm`) for the duplicate
  rule.
- Its strings have no escapes: a string ends at the next `"`. A backslash in
  a string is refused (the host would read another string than the board).
- Names are letters, digits and `_`; values are `n`/`null`, `t`/`true`,
  `f`/`false` (any case; the board takes any word starting with n, t or f,
  the host only these), `""` (a GET too), a string, a JSON number, or an
  object. Arrays (the board answers 116), leading `+` or `.`, `{}`, and text
  after the closing brace are refused.
- Numbers are finite and below `numbers.BOARD_LIMIT` (BAD_NUMBER).
"""

from __future__ import annotations

import functools
import re
from collections.abc import Mapping
from typing import Any

from hostd.protocol.numbers import check_finite
from hostd.protocol.refusals import InvalidCommand, Refusal

Value = None | bool | int | float | str | dict[str, Any]

_NAME = re.compile(r'"([A-Za-z0-9_]+)"|([A-Za-z0-9_]+)')
_NUMBER = re.compile(r"-?(?:0|[1-9][0-9]*)(?:\.[0-9]+)?(?:[eE][-+]?[0-9]+)?")
_INTEGER = re.compile(r"-?[0-9]+")
_WORD = re.compile(r"[A-Za-z]+")
_STRING = re.compile(r'"([^"\\]*)"')
_LITERALS: dict[str, Value] = {
    "n": None,
    "null": None,
    "t": True,
    "true": True,
    "f": False,
    "false": False,
}
_SPACE = " \t"


def read_relaxed(text: str) -> Mapping[str, Value]:
    """The object a relaxed JSON line means, names lower-cased, in the board's order.

    Raises InvalidCommand (UNREADABLE, DUPLICATE_KEY or BAD_NUMBER) for a line
    the host cannot read exactly as the board will. The object is shared
    (lines are read again and again: a dashboard's polls, a request's
    validation, classification and encoding): read it, never change it.
    """
    return _read(text)


@functools.lru_cache(maxsize=1024)
def _read(text: str) -> dict[str, Value]:
    obj = _Reader(text).line()
    seen: dict[str, tuple[str, ...]] = {}
    for names, _ in board_pairs(obj):
        for name in names:
            if name in seen:
                raise InvalidCommand(
                    Refusal.DUPLICATE_KEY,
                    f"{_spell(seen[name])} and {_spell(names)} both name {name!r}: "
                    "the board runs both pairs, in order; send one",
                )
        seen.update(dict.fromkeys(names, names))
    return obj


def parse_relaxed(text: str) -> Mapping[str, Value] | None:
    """As `read_relaxed`, but None for a line it refuses."""
    try:
        return read_relaxed(text)
    except InvalidCommand:
        return None


def board_pairs(obj: Mapping[str, Value]) -> list[tuple[tuple[str, ...], Value]]:
    """Every pair as the board runs it: (the names it may be looked up by, its value).

    A top-level pair has its own name; a member of a nested object has its
    own name and its group's prefix plus its name (the board uses the second
    for prefixed groups such as `x`, the first for `sys` and `sr`).
    """
    out: list[tuple[tuple[str, ...], Value]] = []
    for key, value in obj.items():
        out.append(((key,), value))
        if isinstance(value, dict):
            out.extend(((child, key + child), member) for child, member in value.items())
    return out


def is_get(value: Any) -> bool:
    """A value in GET form (`n`, `null`, `""`): the board reads and answers, it sets nothing."""
    return value is None or value == ""


def _spell(names: tuple[str, ...]) -> str:
    return repr(names[0]) if len(names) == 1 else f"{names[0]!r} (in a group, {names[1]!r})"


def _unreadable(reason: str) -> InvalidCommand:
    return InvalidCommand(
        Refusal.UNREADABLE, f"JSON the host cannot read as the board does: {reason}"
    )


class _Reader:
    def __init__(self, text: str) -> None:
        self.s = text
        self.i = 0

    def line(self) -> dict[str, Value]:
        self.space()
        obj = self.obj(None)
        self.space()
        if self.i != len(self.s):
            raise _unreadable(f"text after the closing brace ({self.s[self.i : self.i + 12]!r})")
        return obj

    def peek(self) -> str:
        return self.s[self.i] if self.i < len(self.s) else ""

    def space(self) -> None:
        while self.peek() in _SPACE and self.i < len(self.s):
            self.i += 1

    def expect(self, ch: str) -> None:
        if self.peek() != ch:
            found = repr(self.peek()) if self.peek() else "the end of the line"
            raise _unreadable(f"expected {ch!r} at column {self.i + 1}, found {found}")
        self.i += 1

    def obj(self, group: str | None) -> dict[str, Value]:
        self.expect("{")
        self.space()
        if self.peek() == "}":
            raise _unreadable("an empty object")
        out: dict[str, Value] = {}
        while True:
            self.space()
            key = self.name()
            if key in out:
                where = "" if group is None else f" in {group!r}"
                raise InvalidCommand(
                    Refusal.DUPLICATE_KEY,
                    f"the name {key!r} appears twice{where} (names are case-insensitive): "
                    "the board runs both pairs, in order; send one",
                )
            self.space()
            self.expect(":")
            self.space()
            if self.peek() == "{":
                if group is not None:
                    raise _unreadable("an object inside an object: the board reads two levels")
                value: Value = self.obj(key)
            else:
                value = self.scalar(key)
            out[key] = value
            self.space()
            if self.peek() == ",":
                if isinstance(value, dict):
                    raise _unreadable(
                        f"a pair after the object {key!r}: the board reads every later pair "
                        "as a member of that group"
                    )
                self.i += 1
                continue
            self.expect("}")
            return out

    def name(self) -> str:
        m = _NAME.match(self.s, self.i)
        if m is None:
            raise _unreadable(f"a name must be letters, digits or '_' (column {self.i + 1})")
        self.i = m.end()
        return (m.group(1) or m.group(2)).lower()

    def scalar(self, key: str) -> Value:
        ch = self.peek()
        if ch == '"':
            m = _STRING.match(self.s, self.i)
            if m is None:
                raise _unreadable(
                    f"the string of {key!r} has a backslash or no closing quote "
                    "(the board's strings have no escapes)"
                )
            self.i = m.end()
            return m.group(1)
        if ch == "-" or "0" <= ch <= "9":
            m = _NUMBER.match(self.s, self.i)
            if m is None:
                raise _unreadable(f"the number of {key!r} is not a plain JSON number")
            self.i = m.end()
            return _number(m.group(), key)
        m = _WORD.match(self.s, self.i)
        if m is not None and m.group().lower() in _LITERALS:
            self.i = m.end()
            return _LITERALS[m.group().lower()]
        if ch == "[":
            raise _unreadable(f"the value of {key!r} is an array (the board answers 116)")
        raise _unreadable(f"the value of {key!r} is not n, t, f, a number, a string or an object")


def _number(text: str, key: str) -> int | float:
    try:
        value: int | float = int(text) if _INTEGER.fullmatch(text) else float(text)
    except ValueError:  # more digits than Python converts
        raise InvalidCommand(Refusal.BAD_NUMBER, f"the number of {key!r} is too long") from None
    check_finite(value, f"the value of {key!r}")
    return value
