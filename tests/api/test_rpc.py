"""JSON-RPC rules as plain function calls: no socket, no server."""

from __future__ import annotations

import json
import math
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

    m = Methods()
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
    [b"[" * 100_000 + b"]" * 100_000, b"1" * 5000, b"", b'{"a": Infinity}'],
    ids=["too-deep", "too-many-digits", "empty", "infinity"],
)
async def test_json_python_would_choke_on_or_accept_loosely_is_a_parse_error(line: bytes) -> None:
    answer = await call(line)
    assert answer["error"]["code"] == -32700
    assert answer["id"] is None


@pytest.mark.asyncio
async def test_a_float_id_is_echoed() -> None:
    assert (await call('{"jsonrpc":"2.0","method":"where","id":1.5}'))["id"] == 1.5


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


def test_only_single_requests_for_immediate_methods_skip_the_task() -> None:
    class P(BaseModel):
        model_config = ConfigDict(extra="forbid")
        machine: str

    async def hold(p: P) -> dict[str, object]:
        return {}

    table = rpc.Methods()
    table.register("machine.feedhold", P, hold, immediate=True)
    table.register("machine.status", P, hold)
    line = b'{"jsonrpc":"2.0","id":1,"method":"machine.feedhold","params":{"machine":"m"}}'
    assert rpc.is_immediate(line, table)
    assert not rpc.is_immediate(line.replace(b"feedhold", b"status"), table)
    assert not rpc.is_immediate(b"[" + line + b"]", table)  # a batch goes the usual way
    assert not rpc.is_immediate(b'{"method":"machine.feedhold"', table)  # broken JSON
    assert not rpc.is_immediate(b'{"method":"x","params":"machine.feedhold"}', table)
