"""The controller-line parser never raises and always says what a line is, keeping its bytes."""

from __future__ import annotations

import json
from typing import Any, get_args

from hypothesis import example, given
from hypothesis import strategies as st

from hostd.protocol.messages import Message
from hostd.protocol.parser import parse_line
from tests.fuzz.strategies import dumps, fuzz, json_values

MESSAGE_TYPES = get_args(Message)

# Lines shaped like what a g2core board sends, with the values gone wrong.
footers = st.lists(json_values | st.integers(-3, 300), max_size=5)
board_lines = st.one_of(
    st.builds(lambda r, f: {"r": r, "f": f}, json_values, footers),
    st.builds(
        lambda r, f: {"r": r, "f": f}, st.dictionaries(st.text(max_size=5), json_values), footers
    ),
    st.builds(lambda sr: {"sr": sr}, json_values),
    st.builds(lambda er: {"er": er}, json_values),
    st.builds(
        lambda q: {"qr": q[0], "qi": q[1], "qo": q[2]},
        st.tuples(json_values, json_values, json_values),
    ),
    st.builds(
        lambda banner: {"r": {**banner, "msg": "SYSTEM READY"}, "f": [1, 0, 1]},
        st.dictionaries(st.sampled_from(["fv", "fb", "hp", "hv", "id"]), json_values),
    ),
    st.dictionaries(st.text(max_size=4), json_values, max_size=3),
    json_values,
)


def _check(raw: bytes) -> None:
    msg = parse_line(raw)
    assert isinstance(msg, MESSAGE_TYPES)
    assert msg.raw == raw


@fuzz(600)
@given(st.binary(max_size=300))
@example(b"{" * 100_000)  # nesting deep enough to blow the recursion limit
@example(b"[" * 100_000)
@example(b"\xff\xfe{")
@example(b'{"r":{},"f":[1,0,1e999]}')
def test_any_bytes_are_one_message_that_keeps_them(raw: bytes) -> None:
    _check(raw)


# 200, not 600: nearly all its CPU is hypothesis drawing nested JSON; a parser that
# read a non-object "r" body failed it within 60 examples (docs/testing.md,
# "Fourth round").
@fuzz(200)
@given(board_lines)
def test_board_shaped_json_is_one_message_that_keeps_it(obj: Any) -> None:
    _check(dumps(obj))
    _check(json.dumps(obj, ensure_ascii=False).encode("utf-8", "surrogatepass"))


@fuzz(200)
@given(board_lines, st.integers(0, 40), st.binary(min_size=1, max_size=3))
def test_a_corrupted_board_line_is_still_one_message(obj: Any, at: int, noise: bytes) -> None:
    raw = dumps(obj)
    cut = at % (len(raw) + 1)
    _check(raw[:cut] + noise + raw[cut:])
