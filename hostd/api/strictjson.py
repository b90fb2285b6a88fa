"""Strict JSON for the API's requests: one decoder, made once (rpc.py reads each line
with it).

- Numbers are I-JSON's (RFC 7493): integers within +-(2**53 - 1), floats finite. A
  number beyond them is read as an `OutOfRange`, kept as its text, so that the request
  can still be answered with its own id and no handler ever sees it.
- NaN, Infinity and -Infinity are not JSON: refused.
- An object names each member once (RFC 8259, 4): one that gives a name twice is
  refused, where Python's json would keep the last.

Each is a ValueError (json.JSONDecodeError for the syntax, RecursionError for nesting
too deep), which rpc.py answers -32700.
"""

from __future__ import annotations

import json
import math
from typing import Any, Final

MAX_SAFE_INTEGER: Final = 9_007_199_254_740_991


class OutOfRange:
    """A number of a request beyond I-JSON's range, kept as its text and never used.

    The parser makes one of these instead of the number, so that the request
    can still be read and answered with its own id (-32602), and no handler
    or pydantic model ever sees 10**400 or infinity.
    """

    __slots__ = ("text",)

    def __init__(self, text: str) -> None:
        self.text = text if len(text) <= 24 else text[:20] + "..."

    def __repr__(self) -> str:
        return f"OutOfRange({self.text!r})"


def _reject_constant(name: str) -> Any:
    raise ValueError(f"{name} is not JSON")


def _parse_int(text: str) -> int | OutOfRange:
    # JSON has no leading zeros: 15 digits always fit, 16 may (2**53 - 1 has 16). The
    # length test comes first so that 5000 digits never reach int() (and its digit limit).
    if len(text) <= 15:
        return int(text)
    if len(text) <= 17:
        value = int(text)
        if -MAX_SAFE_INTEGER <= value <= MAX_SAFE_INTEGER:
            return value
    return OutOfRange(text)


def _parse_float(text: str) -> float | OutOfRange:
    value = float(text)
    return value if math.isfinite(value) else OutOfRange(text)  # 1e400 is inf to float()


def _unique_object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """An object whose names are unique (RFC 8259, 4): `{"method":"machine.status",
    "method":"machine.reset"}` is refused, not read as its last name says."""
    obj = dict(pairs)
    if len(obj) != len(pairs):
        seen: set[str] = set()
        for name, _ in pairs:
            if name in seen:
                raise ValueError(f"the name {json.dumps(name)} is given twice in one object")
            seen.add(name)
    return obj


# Made once: `json.loads` with any option builds a JSONDecoder and its scanner every call
# (the same decoder, so the same values and errors).
_DECODER = json.JSONDecoder(
    parse_constant=_reject_constant,
    parse_int=_parse_int,
    parse_float=_parse_float,
    object_pairs_hook=_unique_object,
)


def read(text: str) -> Any:
    """The JSON value of `text`, strictly (see the module)."""
    return _DECODER.decode(text)
