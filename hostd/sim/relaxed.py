"""g2core's relaxed JSON input, read the way the board reads it (g2core.md section 1).

The board first normalises the line (every character up to space, and DEL,
is dropped and the rest lower-cased, except inside a G-code comment in
parentheses), then reads name/value pairs: names quoted or not; a value
starting with `n`, or `""`, is null (a GET); `t`/`f` start true/false;
numbers start with a digit or `-`; strings are quoted and have no escapes;
an object nests. Anything else is a syntax error (status 111).

This is the simulator's own reader, kept apart from the daemon's
(hostd.protocol.relaxed) on purpose: a test double that shared the code under
test could not catch its mistakes.
"""

from __future__ import annotations

import re

Value = None | bool | float | str | dict[str, "Value"]

_NUMBER = re.compile(r"-?(?:\d+\.?\d*|\.\d+)(?:e[-+]?\d+)?")
_WORD = re.compile(r"[a-z]*")


class RelaxedJsonError(ValueError):
    """The line is not JSON the board can read."""


def normalize(text: str) -> str:
    """Drop whitespace and control characters, lower-case outside comments."""
    out: list[str] = []
    in_comment = False
    for ch in text:
        if in_comment:
            if ch == ")":
                in_comment = False
            out.append(ch)
            continue
        if ch == "(":
            in_comment = True
        if ch <= " " or ch == "\x7f":
            continue
        out.append(ch.lower())
    return "".join(out)


def parse(text: str) -> dict[str, Value]:
    """The object a line means, in the order its pairs were written."""
    return _Reader(normalize(text)).document()


class _Reader:
    def __init__(self, text: str) -> None:
        self.s = text
        self.i = 0

    def document(self) -> dict[str, Value]:
        obj = self.obj()
        # The board stops at the closing brace; whatever follows is ignored.
        return obj

    def peek(self) -> str:
        return self.s[self.i] if self.i < len(self.s) else ""

    def expect(self, ch: str) -> None:
        if self.peek() != ch:
            raise RelaxedJsonError(f"expected {ch!r} at {self.i}")
        self.i += 1

    def obj(self) -> dict[str, Value]:
        self.expect("{")
        out: dict[str, Value] = {}
        if self.peek() == "}":
            self.i += 1
            return out
        while True:
            key = self.key()
            self.expect(":")
            out[key] = self.value()
            sep = self.peek()
            self.i += 1
            if sep == "}":
                return out
            if sep != ",":
                raise RelaxedJsonError(f"expected ',' or '}}' at {self.i - 1}")

    def key(self) -> str:
        quoted = self.peek() == '"'
        if quoted:
            self.i += 1
        start = self.i
        while self.peek() not in ('"', ":", ""):
            if self.peek() in "{},":
                raise RelaxedJsonError(f"bad name at {start}")
            self.i += 1
        key = self.s[start : self.i]
        if quoted:
            self.expect('"')
        if not key:
            raise RelaxedJsonError(f"empty name at {start}")
        return key

    def value(self) -> Value:
        ch = self.peek()
        if ch == "{":
            return self.obj()
        if ch == '"':
            end = self.s.find('"', self.i + 1)
            if end < 0:
                raise RelaxedJsonError("unterminated string")
            text = self.s[self.i + 1 : end]
            self.i = end + 1
            return text if text else None  # "" is a GET
        if ch in ("n", "t", "f"):
            m = _WORD.match(self.s, self.i)
            assert m is not None
            self.i = m.end()
            return None if ch == "n" else ch == "t"
        if ch == "-" or ch.isdigit():
            m = _NUMBER.match(self.s, self.i)
            if m is None or self.s[m.end() : m.end() + 1] not in (",", "}"):
                raise RelaxedJsonError(f"bad number at {self.i}")
            self.i = m.end()
            return float(m.group())
        raise RelaxedJsonError(f"bad value at {self.i}")
