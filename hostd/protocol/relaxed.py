"""Read g2core's relaxed JSON input the way the board does.

The board accepts `{xvm:n}`, `{clear:n}`, `{sr:{posx:t}}`: unquoted keys,
`n` for null (a GET), `t`/`f` for true/false. The daemon must understand a
client's line exactly as the board will, to classify it before sending.
"""

from __future__ import annotations

import json
import re
from typing import Any

# A bare word outside a string: a key, or one of the board's literals.
_TOKEN = re.compile(r'"(?:[^"\\]|\\.)*"|[A-Za-z_$][A-Za-z0-9_.$]*')
_LITERALS = {"n": "null", "null": "null", "t": "true", "true": "true", "f": "false"}
_LITERALS["false"] = "false"


def parse_relaxed(text: str) -> dict[str, Any] | None:
    """The object a relaxed JSON line means, keys lower-cased; None if it is not one."""
    out: list[str] = []
    pos = 0
    for m in _TOKEN.finditer(text):
        out.append(text[pos : m.start()])
        token = m.group()
        if token.startswith('"'):
            out.append(token)
        elif _followed_by_colon(text, m.end()):
            out.append(json.dumps(token))
        elif token.lower() in _LITERALS:
            out.append(_LITERALS[token.lower()])
        else:
            return None
        pos = m.end()
    out.append(text[pos:])
    try:
        obj = json.loads("".join(out))
    except (ValueError, RecursionError):
        return None
    if not isinstance(obj, dict):
        return None
    return {str(k).lower(): v for k, v in obj.items()}


def is_get(value: Any) -> bool:
    """A value in GET form: the board reads and answers, it changes nothing."""
    return value is None or value == "" or (isinstance(value, str) and value.lower() == "n")


def _followed_by_colon(text: str, end: int) -> bool:
    rest = text[end:].lstrip()
    return rest.startswith(":")
