"""What the fuzz tests share: a deterministic budget and generators of JSON-ish input.

Every test runs with `derandomize=True` (the same examples on every run, so
`make test` is reproducible), no deadline (the 2-vCPU machines are noisy)
and no example database (nothing is written into the tree).
"""

from __future__ import annotations

import json
from typing import Any

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st


def fuzz(max_examples: int) -> settings:
    return settings(
        max_examples=max_examples,
        derandomize=True,
        deadline=None,
        database=None,
        suppress_health_check=[HealthCheck.too_slow],
    )


# Text as a client's JSON can carry it: any code point, lone surrogates included
# (JSON's "\ud800" escape decodes to one).
any_text = st.text(st.characters(exclude_categories=()), max_size=40)


def json_of(text: st.SearchStrategy[str]) -> st.SearchStrategy[Any]:
    """Any JSON value (no NaN or infinities), its strings and keys drawn from `text`."""
    floats = st.floats(allow_nan=False, allow_infinity=False)
    scalars = st.none() | st.booleans() | st.integers() | floats | text
    return st.recursive(
        scalars,
        lambda inner: st.lists(inner, max_size=4) | st.dictionaries(text, inner, max_size=4),
        max_leaves=12,
    )


json_values = json_of(any_text)


def dumps(value: Any) -> bytes:
    """Compact JSON, ASCII-escaped (so lone surrogates survive as escapes)."""
    return json.dumps(value, separators=(",", ":")).encode()
