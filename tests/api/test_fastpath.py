"""The realtime fast path's own reading of a request (`fastpath.Shape`).

It reads a request with a regular expression instead of the JSON parser and
pydantic, so it must never read a line differently from them: whatever it
reads, the parser and `MachineParams` read the same (method, machine, id), and
whatever it declines goes the general way, which answers it as before.
"""

from __future__ import annotations

from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from hostd.api import rpc
from hostd.api.fastpath import Shape
from hostd.api.methods.params import MachineParams


async def _handler(p: MachineParams) -> dict[str, Any]:
    return {}


def _table() -> rpc.Methods:
    table = rpc.Methods()
    table.register("machine.feedhold", MachineParams, _handler, immediate=True)
    table.register("machine.cycle_start", MachineParams, _handler, immediate=True)
    return table


SHAPE = Shape(_table())


def _general(line: bytes) -> tuple[str, str, Any] | None:
    """What the parser and the params model make of the line: (method, machine, id), or None
    when the general way would not run it as a request of a realtime method."""
    incoming = rpc.decode(line.rstrip(b"\n"))
    message = incoming.message
    if incoming.reply is not None or not isinstance(message, dict):
        return None
    if set(message) != {"jsonrpc", "id", "method", "params"} or message["jsonrpc"] != "2.0":
        return None
    if not rpc._valid_id(message["id"]) or message["method"] not in SHAPE_NAMES:
        return None
    try:
        params = MachineParams.model_validate(message["params"])
    except ValidationError:
        return None
    return message["method"], params.machine, message["id"]


SHAPE_NAMES = {"machine.feedhold", "machine.cycle_start"}


def _read(line: bytes) -> tuple[str, str, Any] | None:
    read = SHAPE.read(line)
    return None if read is None else (read[1], read[2], read[3])


@pytest.mark.parametrize(
    "line",
    [
        # bench/client.py's way: compact, id before method
        b'{"jsonrpc":"2.0","id":7,"method":"machine.feedhold","params":{"machine":"bench"}}\n',
        # json.dumps' default separators, the CLI's order (method before id)
        b'{"jsonrpc": "2.0", "method": "machine.cycle_start", "id": 8, '
        b'"params": {"machine": "m-1.a_b"}}\n',
        b' {\t"params" : { "machine" : "m" } ,"id":"abc","method":"machine.feedhold",'
        b'"jsonrpc":"2.0"}\r\n',
        b'{"jsonrpc":"2.0","id":-3,"method":"machine.feedhold","params":{"machine":"m"}}\n',
        b'{"jsonrpc":"2.0","id":"","method":"machine.feedhold","params":{"machine":"m"}}\n',
        b'{"jsonrpc":"2.0","id":999999999999999,"method":"machine.feedhold","params":'
        b'{"machine":"' + b"m" * 64 + b'"}}\n',  # the longest id and machine it reads
    ],
)
def test_the_usual_shapes_are_read_as_the_parser_reads_them(line: bytes) -> None:
    assert _read(line) is not None
    assert _read(line) == _general(line)


@pytest.mark.parametrize(
    "line",
    [
        # valid, but not the shape: the general way answers them
        b'{"jsonrpc":"2.0","id":1,"method":"machine.feedhold","params":{"machine":"m\\u0031"}}\n',
        b'{"jsonrpc":"2.0","method":"machine.feedhold","params":{"machine":"m"}}\n',  # notice
        b'{"jsonrpc":"2.0","id":1,"method":"machine.feedhold","params":["m"]}\n',
        b'{"jsonrpc":"2.0","id":1.5,"method":"machine.feedhold","params":{"machine":"m"}}\n',
        b'[{"jsonrpc":"2.0","id":1,"method":"machine.feedhold","params":{"machine":"m"}}]\n',
        # not valid, or not a realtime method: the general way refuses or runs them
        b'{"jsonrpc":"2.0","id":1,"method":"machine.status","params":{"machine":"m"}}\n',
        b'{"jsonrpc":"1.0","id":1,"method":"machine.feedhold","params":{"machine":"m"}}\n',
        b'{"jsonrpc":"2.0","jsonrpc":"2.0","method":"machine.feedhold","params":{"machine":"m"}}\n',
        b'{"jsonrpc":"2.0","id":1,"method":"machine.feedhold","params":{"machine":""}}\n',
        b'{"jsonrpc":"2.0","id":1,"method":"machine.feedhold","params":{"machine":"a b"}}\n',
        b'{"jsonrpc":"2.0","id":1,"method":"machine.feedhold","params":{"machine":"m","x":1}}\n',
        b'{"jsonrpc":"2.0","id":{"machine":"m"},"method":"machine.feedhold","params":'
        b'{"machine":"m"}}\n',
        b'{"jsonrpc":"2.0","id":1234567890123456,"method":"machine.feedhold","params":'
        b'{"machine":"m"}}\n',
        b'{"jsonrpc":"2.0","id":01,"method":"machine.feedhold","params":{"machine":"m"}}\n',
        b'{"jsonrpc":"2.0","id":1,"method":"machine.feedhold","params":{"machine":"m"}}',
        b'{"jsonrpc":"2.0","id":1,"method":"machine.feedhold","params":{"machine":"m"}}\n\n',
        b'{"jsonrpc":"2.0","id":1,"method":"machine.feedhold","params":{"machine":"'
        + b"m" * 65
        + b'"}}\n',
    ],
)
def test_anything_else_is_left_to_the_general_way(line: bytes) -> None:
    assert SHAPE.read(line) is None


_KEYS = ["jsonrpc", "id", "method", "params"]
_BLANK = st.sampled_from(["", " ", "\t", "\r", "  "])  # JSON's whitespace but the newline
_TEXT = "ab1_.-"  # an id's characters
_VALID = {
    "jsonrpc": st.just('"2.0"'),
    "id": st.one_of(
        st.integers(-(2**53), 2**53).map(str),
        st.text(alphabet=_TEXT, max_size=64).map(lambda s: f'"{s}"'),
    ),
    "method": st.sampled_from(['"machine.feedhold"', '"machine.cycle_start"']),
    "params": st.text(alphabet=_TEXT, min_size=1, max_size=64).map(
        lambda s: '{"machine":"' + s + '"}'
    ),
}
_NEAR = {  # each member's values that are invalid, or valid but not the shape's
    "jsonrpc": st.sampled_from(['"2"', "2.0", '"2.0 "', "null"]),
    "id": st.one_of(
        st.integers(-(2**60), 2**60).map(str),
        st.text(alphabet=_TEXT + 'é \\"/{}', max_size=66).map(lambda s: f'"{s}"'),
        st.sampled_from(["null", "1.0", "1e3", "true", "-0", "00", "-", "{}"]),
    ),
    "method": st.sampled_from(['"machine.status"', '"x"', "1", '"machine.feedhold "']),
    "params": st.one_of(
        st.text(alphabet=_TEXT + 'é \\"\n/', max_size=66).map(lambda s: '{"machine":"' + s + '"}'),
        st.sampled_from(['{"machine":"m","x":1}', '["m"]', "{}", '{"Machine":"m"}']),
    ),
}


@st.composite
def _requests(draw: st.DrawFn) -> bytes:
    """Request lines at and near the shape: members valid or not, in any order, blanks
    that JSON takes or not."""
    keys = draw(
        st.one_of(st.permutations(_KEYS), st.lists(st.sampled_from(_KEYS), min_size=3, max_size=5))
    )
    odd = draw(st.integers(0, 3)) == 0  # now and then, blanks JSON does not take
    blank = st.one_of(_BLANK, st.sampled_from(["\n", "\f", "\v"])) if odd else _BLANK

    def value(key: str) -> str:
        return draw(st.one_of(_VALID[key], _NEAR[key]) if draw(st.booleans()) else _VALID[key])

    members = [f'"{k}"{draw(blank)}:{draw(blank)}{value(k)}' for k in keys]
    body = f"{draw(blank)},{draw(blank)}".join(members)
    return f"{draw(blank)}{{{draw(blank)}{body}{draw(blank)}}}{draw(blank)}\n".encode()


@settings(max_examples=300, deadline=None)
@given(_requests())
def test_whatever_it_reads_the_parser_and_the_model_read_alike(line: bytes) -> None:
    read = _read(line)
    if read is not None:
        assert read == _general(line)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=200))
def test_garbage_is_never_read_as_a_request(data: bytes) -> None:
    read = _read(data)
    if read is not None:
        assert read == _general(data)


def test_long_lines_of_blanks_are_turned_down() -> None:
    # The expression has no two repeats side by side nor nested, so it scans these in
    # linear time (a catastrophic backtrack would hang here).
    for body in (b" " * 200_000, b'"id"' + b" " * 200_000, b'"id":1,' * 30_000):
        assert SHAPE.read(b"{" + body + b"x}\n") is None
