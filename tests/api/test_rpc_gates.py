"""JSON-RPC gates that mutants of rpc.py once slipped through (docs/api.md, "Numbers and ids").

Through a real ApiServer on a Unix socket where a client could send it; the
error encoding of a handler's own exception by `dispatch`, as no client can
make one.
"""

from __future__ import annotations

import json
import math
from typing import Any

import pytest

from hostd.api.rpc import INTERNAL_ERROR, Methods, RpcError, dispatch
from tests.api.conftest import Conn

pytestmark = pytest.mark.asyncio

OUT_OF_RANGE = "out of range: integers must be within +-9007199254740991, floats finite"


@pytest.mark.parametrize(
    "number", ["-9007199254740992", "-9999999999999999"], ids=["minus-2**53", "17-chars"]
)
async def test_a_negative_integer_just_past_the_safe_range_never_reaches_a_handler(
    conn: Conn, number: str
) -> None:
    """17 characters with the sign: the parser's range check, not its length test, refuses it."""
    line = f'{{"jsonrpc":"2.0","method":"add","params":{{"a":{number},"b":0}},"id":9}}\n'
    await conn.send_raw(line.encode())
    answer = await conn.recv()
    assert answer["id"] == 9
    assert answer["error"]["code"] == -32602
    assert answer["error"]["data"] == [
        {"loc": ["a"], "msg": f"number {number} {OUT_OF_RANGE}", "type": "number_out_of_range"}
    ]
    assert await conn.call("add", {"a": -9007199254740991, "b": 0}) == {
        "jsonrpc": "2.0",
        "result": -9007199254740991,
        "id": 1,
    }


@pytest.mark.parametrize(
    "line",
    [
        b'{"jsonrpc":"2.0","method":"echo","params":{"text":"G0 X1\xff"},"id":1}\n',
        b'{"jsonrpc":"2.0","method":"echo","params":{"text":"\xc3"},"id":1}\n',
        b'{"jsonrpc":"2.0","method":"echo","params":{"text":"\xed\xa0\x80"},"id":1}\n',
    ],
    ids=["stray-byte", "cut-sequence", "encoded-surrogate"],
)
async def test_bytes_that_are_not_utf8_inside_a_string_are_a_parse_error(
    conn: Conn, line: bytes
) -> None:
    await conn.send_raw(line)
    answer = await conn.recv()
    assert answer["id"] is None
    assert answer["error"]["code"] == -32700
    assert answer["error"]["message"].startswith("parse error: not UTF-8 at byte ")


@pytest.mark.parametrize("char", ["\t", "\x00", "\x1b", "\r"], ids=["tab", "nul", "esc", "cr"])
async def test_a_raw_control_character_inside_a_string_is_a_parse_error(
    conn: Conn, char: str
) -> None:
    """Strict JSON: a control character in a string must be escaped (RFC 8259, 7)."""
    line = f'{{"jsonrpc":"2.0","method":"echo","params":{{"text":"G0{char}X1"}},"id":1}}\n'
    await conn.send_raw(line.encode())
    answer = await conn.recv()
    assert answer["id"] is None
    assert answer["error"]["code"] == -32700
    assert (await conn.call("echo", {"text": f"G0{char}X1"}))["result"] == {"text": f"G0{char}X1"}


@pytest.mark.parametrize(
    "line",
    [
        b'{"jsonrpc":"1.0","method":"count","id":1.5}\n',
        b'{"method":"count","id":1e400}\n',
        b'{"jsonrpc":"2","method":"count","id":9007199254740992}\n',
        b'{"method":"count","id":[1]}\n',
    ],
    ids=[
        "wrong-version-fraction",
        "no-version-overflow",
        "wrong-version-2**53",
        "no-version-array",
    ],
)
async def test_an_invalid_id_is_never_echoed_whatever_else_is_wrong(
    conn: Conn, line: bytes
) -> None:
    await conn.send_raw(line)
    answer = await conn.recv()
    assert answer == {
        "jsonrpc": "2.0",
        "error": {"code": -32600, "message": 'invalid request: "jsonrpc" must be "2.0"'},
        "id": None,
    }
    assert (await conn.call("echo", {"text": "still here"}))["result"] == {"text": "still here"}


class _Odd(Exception):
    """An exception a library might raise, with `code` and `message` of other types."""

    def __init__(self, code: Any, message: Any) -> None:
        super().__init__("odd")
        self.code = code
        self.message = message


def _raising(exc: Exception) -> Methods:
    async def fail() -> None:
        raise exc

    methods = Methods()
    methods.register("fail", None, fail)
    return methods


async def _answer(methods: Methods) -> Any:
    raw = await dispatch(b'{"jsonrpc":"2.0","method":"fail","id":3}', methods, None)
    assert raw is not None
    return json.loads(raw)


@pytest.mark.parametrize(
    "data",
    [object(), {"position": math.nan}, {"far": math.inf}],
    ids=["object", "nan", "infinity"],
)
async def test_error_data_that_is_not_strict_json_is_left_out_not_a_crash(data: Any) -> None:
    answer = await _answer(_raising(RpcError(1005, "the board refused it", data)))
    assert answer == {
        "jsonrpc": "2.0",
        "error": {"code": 1005, "message": "the board refused it"},
        "id": 3,
    }


@pytest.mark.parametrize(
    ("code", "message"),
    [("E42", "a string code"), (True, "a bool code"), (1003, None), (1003.0, "a float code")],
    ids=["str-code", "bool-code", "no-message", "float-code"],
)
async def test_an_exception_whose_code_is_not_an_error_code_is_an_internal_error(
    code: Any, message: Any
) -> None:
    """JSON-RPC's error code is an integer and its message a string: anything else is a bug."""
    answer = await _answer(_raising(_Odd(code, message)))
    assert answer["error"] == {"code": INTERNAL_ERROR, "message": "internal error"}
    assert answer["id"] == 3


@pytest.mark.parametrize(
    "line",
    [
        b'{"jsonrpc":"2.0","method":"echo","method":"add","params":{"a":1,"b":2},"id":1}\n',
        b'{"jsonrpc":"2.0","method":"add","params":{"a":1,"a":5,"b":2},"id":1}\n',
        b'[{"jsonrpc":"2.0","method":"echo","params":{"text":"x"},"id":1,"id":2}]\n',
    ],
    ids=["method-twice", "param-twice", "id-twice-in-a-batch"],
)
async def test_a_name_given_twice_in_one_object_is_a_parse_error(conn: Conn, line: bytes) -> None:
    """RFC 8259: names SHOULD be unique, and a reader may take the first or the last. A
    request that names two methods, or one param twice, runs neither."""
    await conn.send_raw(line)
    answer = await conn.recv()
    assert answer["id"] is None
    assert answer["error"]["code"] == -32700
    assert "given twice in one object" in answer["error"]["message"]
    assert (await conn.call("add", {"a": 1, "b": 2}))["result"] == 3  # the connection goes on
