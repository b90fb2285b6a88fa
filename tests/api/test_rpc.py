"""JSON-RPC rules as plain function calls: no socket, no server."""

from __future__ import annotations

import json
import math
import struct
from typing import Any

import pytest
from pydantic import BaseModel, ConfigDict

from hostd.api import rpc
from hostd.api.rpc import (
    INTERNAL_ERROR,
    MAX_BATCH,
    Methods,
    RpcError,
    current_context,
    dispatch,
    encode_notification,
)


class Point(BaseModel):
    model_config = ConfigDict(extra="forbid")
    x: float = 0.0


class Lax(BaseModel):
    x: int


class JobRef(BaseModel):
    model_config = ConfigDict(extra="forbid")
    job: int
    tags: list[Any] = []


def table() -> Methods:
    async def nan() -> float:
        return math.nan

    async def unserialisable() -> object:
        return object()

    async def who() -> Any:
        return current_context()

    async def refuse(p: Point) -> None:
        raise RpcError(1004, "no such job", {"job": 3})

    async def where(p: Point) -> Point:
        return p

    async def store(p: JobRef) -> str:
        # What SQLite does with an integer: a signed 64-bit slot, OverflowError past it.
        return struct.pack("<q", p.job).hex()

    m = Methods()
    m.register("store", JobRef, store)
    m.register("nan", None, nan)
    m.register("unserialisable", None, unserialisable)
    m.register("who", None, who)
    m.register("refuse", Point, refuse)
    m.register("where", Point, where)
    return m


async def call(line: str | bytes, context: object = None) -> Any:
    raw = line if isinstance(line, bytes) else line.encode()
    answer = await dispatch(raw, table(), context)
    return None if answer is None else json.loads(answer)


def test_a_method_name_is_registered_once() -> None:
    m = table()
    with pytest.raises(ValueError, match="already registered"):
        m.register("where", Point, m["where"].handler)


def test_a_params_model_must_forbid_unknown_fields() -> None:
    async def lax(p: Lax) -> None:
        return None

    with pytest.raises(ValueError, match="extra='forbid'"):
        Methods().register("lax", Lax, lax)


@pytest.mark.asyncio
async def test_the_handler_sees_the_context_given_to_dispatch() -> None:
    answer = await call('{"jsonrpc":"2.0","method":"who","id":1}', context="client-7")
    assert answer["result"] == "client-7"


def test_there_is_no_context_outside_a_call() -> None:
    with pytest.raises(LookupError):
        current_context()


@pytest.mark.asyncio
async def test_params_default_when_absent_and_the_result_model_is_dumped() -> None:
    assert (await call('{"jsonrpc":"2.0","method":"where","id":1}'))["result"] == {"x": 0.0}
    answer = await call('{"jsonrpc":"2.0","method":"where","params":null,"id":1}')
    assert answer["result"] == {"x": 0.0}


@pytest.mark.asyncio
async def test_an_rpc_error_from_the_handler_is_the_answer() -> None:
    answer = await call('{"jsonrpc":"2.0","method":"refuse","id":"r"}')
    assert answer == {
        "jsonrpc": "2.0",
        "error": {"code": 1004, "message": "no such job", "data": {"job": 3}},
        "id": "r",
    }


@pytest.mark.asyncio
@pytest.mark.parametrize("method", ["nan", "unserialisable"])
async def test_a_result_that_is_not_strict_json_is_an_internal_error(method: str) -> None:
    answer = await call(f'{{"jsonrpc":"2.0","method":"{method}","id":1}}')
    assert answer["error"]["code"] == INTERNAL_ERROR


@pytest.mark.asyncio
@pytest.mark.parametrize(
    "line",
    [b"[" * 100_000 + b"]" * 100_000, b"", b'{"a": Infinity}', b'{"id": NaN}', b"-Infinity"],
    ids=["too-deep", "empty", "infinity", "nan", "minus-infinity"],
)
async def test_json_python_would_choke_on_or_accept_loosely_is_a_parse_error(line: bytes) -> None:
    answer = await call(line)
    assert answer["error"]["code"] == -32700
    assert answer["id"] is None


@pytest.mark.asyncio
@pytest.mark.parametrize(
    "line",
    [b"1" * 5000, b"1e400", b"[1e400]"],
    ids=["more-digits-than-python-reads", "beyond-a-double", "in-a-batch"],
)
async def test_a_number_too_big_for_anyone_is_still_json_but_not_a_request(line: bytes) -> None:
    answer = await call(line)
    first = answer[0] if isinstance(answer, list) else answer
    assert first["error"]["code"] == -32600
    assert first["id"] is None


@pytest.mark.asyncio
@pytest.mark.parametrize(
    "id",
    ["1.5", "1.0", "1e3", "-0.0", "9007199254740992", "-9007199254740992", "1" + "0" * 400,
     "1e400", "true", "false", "{}", "[]", '{"id": 1}'],
)  # fmt: skip
async def test_an_id_that_is_not_a_string_a_safe_integer_or_null_is_an_invalid_request(
    id: str,
) -> None:
    answer = await call(f'{{"jsonrpc":"2.0","method":"where","id":{id}}}')
    assert answer["error"]["code"] == -32600
    assert answer["error"]["message"] == (
        'invalid request: "id" must be a string, an integer within +-9007199254740991 or null'
    )
    assert answer["id"] is None


@pytest.mark.asyncio
@pytest.mark.parametrize("id", [0, 9007199254740991, -9007199254740991, "", "x" * 1000])
async def test_safe_integer_and_string_ids_are_echoed(id: int | str) -> None:
    line = json.dumps({"jsonrpc": "2.0", "method": "where", "id": id})
    assert (await call(line))["id"] == id


@pytest.mark.asyncio
@pytest.mark.parametrize(
    ("params", "loc", "number"),
    [
        ('{"job": 9007199254740992}', ["job"], "9007199254740992"),
        ('{"job": -1' + "0" * 400 + "}", ["job"], "-1000000000000000000..."),
        ('{"job": 1, "tags": [0, {"a": 1e400}]}', ["tags", 1, "a"], "1e400"),
        ('{"job": 1, "tags": [-1e999]}', ["tags", 0], "-1e999"),
    ],
    ids=["just-past-2**53", "400-digits", "nested-float-overflow", "negative-overflow"],
)
async def test_a_number_out_of_range_in_params_is_invalid_params_not_an_internal_error(
    params: str, loc: list[Any], number: str
) -> None:
    answer = await call(f'{{"jsonrpc":"2.0","method":"store","id":7,"params":{params}}}')
    assert answer["id"] == 7
    assert answer["error"]["code"] == -32602
    assert answer["error"]["data"] == [
        {
            "loc": loc,
            "msg": f"number {number} out of range: integers must be within"
            " +-9007199254740991, floats finite",
            "type": "number_out_of_range",
        }
    ]
    assert answer["error"]["message"].startswith(f"invalid params: {'.'.join(map(str, loc))}: ")


@pytest.mark.asyncio
async def test_the_largest_safe_integer_reaches_the_handler() -> None:
    answer = await call(
        '{"jsonrpc":"2.0","method":"store","id":1,"params":{"job":-9007199254740991}}'
    )
    assert answer["result"] == struct.pack("<q", -(2**53 - 1)).hex()


@pytest.mark.asyncio
async def test_params_nested_as_deep_as_the_parser_allows_are_invalid_params() -> None:
    deep = "[" * 500 + "]" * 500
    answer = await call(f'{{"jsonrpc":"2.0","method":"store","id":1,"params":{{"job":{deep}}}}}')
    assert answer["error"]["code"] == -32602
    answer = await call(
        f'{{"jsonrpc":"2.0","method":"store","id":1,"params":{{"job":1,"tags":{deep}}}}}'
    )
    assert answer["result"] == struct.pack("<q", 1).hex()


@pytest.mark.asyncio
async def test_a_null_id_is_a_request_not_a_notification() -> None:
    answer = await call('{"jsonrpc":"2.0","method":"where","id":null}')
    assert answer == {"jsonrpc": "2.0", "result": {"x": 0.0}, "id": None}


@pytest.mark.asyncio
async def test_a_notification_that_fails_is_silent() -> None:
    assert await call('{"jsonrpc":"2.0","method":"nope"}') is None
    assert await call('{"jsonrpc":"2.0","method":"refuse"}') is None


def test_a_notification_leaves_out_absent_params() -> None:
    assert encode_notification("tick") == b'{"jsonrpc":"2.0","method":"tick"}'
    assert encode_notification("tick", Point(x=1)) == (
        b'{"jsonrpc":"2.0","method":"tick","params":{"x":1.0}}'
    )


@pytest.mark.asyncio
async def test_a_batch_is_capped() -> None:
    one = '{"jsonrpc":"2.0","method":"where","id":1}'
    assert len(await call("[" + ",".join([one] * MAX_BATCH) + "]")) == MAX_BATCH
    answer = await call("[" + ",".join([one] * (MAX_BATCH + 1)) + "]")
    assert answer == {
        "jsonrpc": "2.0",
        "error": {"code": -32600, "message": "invalid request: batch over 1000 requests"},
        "id": None,
    }


@pytest.mark.parametrize(
    ("line", "requests"),
    [
        (b'{"jsonrpc":"2.0","method":"where","id":1}', 1),
        (b"[1, 2, 3]", 3),
        (b'[{"jsonrpc":"2.0","method":"where"}]', 1),
        (b"42", 1),
    ],
)
def test_a_line_costs_one_request_or_its_batch_length(line: bytes, requests: int) -> None:
    incoming = rpc.decode(line)
    assert incoming.reply is None
    assert incoming.requests == requests


@pytest.mark.parametrize("line", [b"nope", b"[]", b"[1, 2, 3, 4]"])
def test_a_line_that_cannot_run_is_answered_at_once_and_costs_nothing(line: bytes) -> None:
    incoming = rpc.decode(line, max_batch=3)
    assert incoming.requests == 0
    assert incoming.reply is not None
    assert json.loads(incoming.reply)["error"]["code"] in (-32700, -32600)


@pytest.mark.asyncio
async def test_the_batch_cap_is_the_callers() -> None:
    one = b'{"jsonrpc":"2.0","method":"where","id":1}'
    answer = await dispatch(b"[" + b",".join([one] * 4) + b"]", table(), None, max_batch=3)
    assert answer is not None
    assert json.loads(answer)["error"] == {
        "code": -32600,
        "message": "invalid request: batch over 3 requests",
    }


def test_only_single_requests_for_immediate_methods_skip_the_task() -> None:
    class P(BaseModel):
        model_config = ConfigDict(extra="forbid")
        machine: str

    async def hold(p: P) -> dict[str, object]:
        return {}

    table = rpc.Methods()
    table.register("machine.feedhold", P, hold, immediate=True)
    table.register("machine.status", P, hold)

    def immediate(line: bytes) -> bool:
        return rpc.is_immediate(rpc.decode(line), table)

    line = b'{"jsonrpc":"2.0","id":1,"method":"machine.feedhold","params":{"machine":"m"}}'
    assert immediate(line)
    assert not immediate(line.replace(b"feedhold", b"status"))
    assert not immediate(b"[" + line + b"]")  # a batch goes the usual way
    assert not immediate(b'{"method":"machine.feedhold"')  # broken JSON
    assert not immediate(b'{"method":"x","params":"machine.feedhold"}')
