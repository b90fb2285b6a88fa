"""JSON-RPC 2.0 without I/O: one line of bytes in, one line of bytes (or nothing) out.

Everything the protocol says lives here, so that every rule can be pinned with
plain function calls; `server.py` only moves lines between sockets and this
module.

The method table (`Methods`) is generic: a name maps to an async handler and
the pydantic model its params are validated with. The API layer registers the
real methods; this module knows nothing about machines.

How a handler learns who called it: `dispatch` takes a `context` (the server
passes its `Client`) and makes it available, for the duration of each handler
call, through `current_context()` (a contextvar, so concurrent requests each
see their own caller). Handlers keep a one-argument signature and only the few
that care (subscriptions) ask; `hostd.api.client.current_client()` is the typed
way to do so. A task a handler spawns inherits the value as it was at spawn
time; it must not rely on it later.

Decisions beyond JSON-RPC 2.0 itself:

- `"params": null` is treated like absent params (lenient; some clients send it).
- A method with a params model takes params by name only: an object, or
  nothing/null/`[]`/`{}` (validated as `{}`). A non-empty array is -32602.
- Requests are parsed as strict JSON (`strictjson.py`): UTF-8 only, no
  NaN/Infinity, no name given twice in an object. Results are
  written as strict JSON too: a NaN in a result is a bug (-32603, logged).
- Numbers are I-JSON's (RFC 7493): integers within +-(2**53 - 1), floats
  finite. Those are the numbers every JSON implementation reads the same; a
  number beyond them (10**400, 1e400) would mean one thing to the client and
  another here, and used as a job id or a distance it reaches code that was
  never meant to see it. Out of range in `params` is -32602 naming where; the
  number is never handed to a handler.
- An `id` is a string, an integer within that range, or null. Anything else
  (a fraction, an object, a bool, 2**53) is -32600 answered with `id: null`:
  JSON-RPC says ids SHOULD NOT have fractional parts, and an id the client
  cannot compare exactly cannot match its request anyway.
- A batch holds at most `max_batch` requests (`MAX_BATCH`, 1000, unless the
  caller says less; the server says its per-client limit); a longer one is one
  -32600 and none of it runs.
- Invalid requests (-32600) and parse errors (-32700) are answered even when
  the request had no `id`, with `id: null`, as the JSON-RPC examples do. Once a
  request is valid and has no `id`, it is a notification: it runs and nothing
  is answered, whatever happens.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Awaitable, Callable, Iterator, Mapping
from contextvars import ContextVar
from dataclasses import dataclass
from typing import Any, Final, TypeVar, overload

import structlog
from pydantic import BaseModel, ValidationError
from pydantic_core import to_jsonable_python

from hostd.api import strictjson
from hostd.api.strictjson import OutOfRange

log = structlog.get_logger(__name__)

PARSE_ERROR: Final = -32700
INVALID_REQUEST: Final = -32600
METHOD_NOT_FOUND: Final = -32601
INVALID_PARAMS: Final = -32602
INTERNAL_ERROR: Final = -32603
# JSON-RPC leaves -32000 to -32099 to the server. hostd's one: a limit is reached (the
# daemon's max_clients, a subscription limit, MQTT's commands running; docs/api.md).
SERVER_FULL: Final = -32000

# Batch elements run concurrently: a cap keeps one line from starting an
# unbounded number of handlers. The server passes its per-client limit instead.
MAX_BATCH: Final = 1000
# The largest integer every JSON implementation represents exactly (2**53 - 1).
MAX_SAFE_INTEGER: Final = strictjson.MAX_SAFE_INTEGER

P = TypeVar("P", bound=BaseModel)

Id = str | int | None
Handler = Callable[..., Awaitable[Any]]


class RpcError(Exception):
    """An error answer: raised by handlers (or by this module) with the code to send.

    Handlers may also raise any exception with an integer `code` and a string
    `message` (the machine layer's errors): it is answered the same way.
    """

    def __init__(self, code: int, message: str, data: Any = None) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.data = data


@dataclass(frozen=True, slots=True)
class Method:
    """One entry of the table: the handler and what its params must look like.

    `params_model` None means the method takes no params and the handler is
    called with no argument; otherwise it is called with the validated model.
    """

    handler: Handler
    params_model: type[BaseModel] | None
    # Never suspends (a realtime byte): the server may run it without a task of its own.
    immediate: bool = False


class Methods(Mapping[str, Method]):
    """The method table: name -> `Method`. Filled once at start-up, then read-only in use."""

    def __init__(self) -> None:
        self._table: dict[str, Method] = {}

    @overload
    def register(
        self,
        name: str,
        params_model: type[P],
        handler: Callable[[P], Awaitable[Any]],
        *,
        immediate: bool = False,
    ) -> None: ...

    @overload
    def register(
        self,
        name: str,
        params_model: None,
        handler: Callable[[], Awaitable[Any]],
        *,
        immediate: bool = False,
    ) -> None: ...

    def register(
        self,
        name: str,
        params_model: type[BaseModel] | None,
        handler: Handler,
        *,
        immediate: bool = False,
    ) -> None:
        """Add a method. Refuses duplicates and params models that would accept unknown fields."""
        if name in self._table:
            raise ValueError(f"method {name!r} is already registered")
        if params_model is not None and params_model.model_config.get("extra") != "forbid":
            # A typo'd field name must be an error for the client, not silently ignored.
            raise ValueError(f"params model of {name!r} must set model_config extra='forbid'")
        self._table[name] = Method(handler, params_model, immediate)

    def __getitem__(self, name: str) -> Method:
        return self._table[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._table)

    def __len__(self) -> int:
        return len(self._table)


_context: ContextVar[object] = ContextVar("hostd_rpc_context")


def current_context() -> object:
    """The `context` given to `dispatch` for the request being handled.

    Raises LookupError outside a handler call.
    """
    return _context.get()


# --- encoding ---------------------------------------------------------------


def _default(obj: Any) -> Any:
    if isinstance(obj, BaseModel):
        return obj.model_dump(mode="json")
    # Dataclasses, enums, datetimes, sets...: pydantic's own rules; raises on anything else.
    return to_jsonable_python(obj)


def encode(message: Any) -> bytes:
    """Compact, strict JSON as UTF-8 bytes, without the line terminator.

    Text with a lone surrogate (JSON's "\\ud800", echoed back in an id or a
    method name) has no UTF-8 form: such a message is written with ASCII
    escapes instead, still valid JSON, still the same value.
    """
    text = _UTF8.encode(message)
    try:
        return text.encode()
    except UnicodeEncodeError:
        return _ASCII.encode(message).encode()


# Made once: json.dumps with any option builds a new encoder at every call, which cost
# more than the encoding itself of a short notification (13.7 against 8.2 us a console
# message; docs/performance.md, issue 30).
_UTF8 = json.JSONEncoder(
    separators=(",", ":"), ensure_ascii=False, allow_nan=False, default=_default
)
_ASCII = json.JSONEncoder(
    separators=(",", ":"), ensure_ascii=True, allow_nan=False, default=_default
)


def encode_error(code: int, message: str, id: Id = None, data: Any = None) -> bytes:
    """An error response. `data` is left out when None, as JSON-RPC allows."""
    error: dict[str, Any] = {"code": code, "message": message}
    if data is not None:
        error["data"] = data
    return encode({"jsonrpc": "2.0", "error": error, "id": id})


def encode_notification(method: str, params: Any = None) -> bytes:
    """A server-to-client notification (no `id`). `params` is left out when None."""
    message: dict[str, Any] = {"jsonrpc": "2.0", "method": method}
    if params is not None:
        message["params"] = params
    return encode(message)


def _encode_result(result: Any, id: Id, method: str) -> bytes:
    try:
        return encode({"jsonrpc": "2.0", "result": result, "id": id})
    except Exception:
        log.exception("result is not JSON-serialisable", method=method, id=id)
        return encode_error(INTERNAL_ERROR, "internal error", id)


def _encode_failure(exc: RpcError, id: Id, method: str) -> bytes:
    try:
        return encode_error(exc.code, exc.message, id, exc.data)
    except Exception:
        log.exception("error data is not JSON-serialisable", method=method, id=id)
        return encode_error(exc.code, exc.message, id)


# --- decoding and validation ------------------------------------------------


def _parse(line: bytes) -> Any:
    """The JSON value on the line, or RpcError(-32700)."""
    try:
        text = line.decode("utf-8")
    except UnicodeDecodeError as e:
        raise RpcError(PARSE_ERROR, f"parse error: not UTF-8 at byte {e.start}") from None
    try:
        return strictjson.read(text)
    except json.JSONDecodeError as e:
        raise RpcError(PARSE_ERROR, f"parse error: {e.msg} at column {e.colno}") from None
    except (ValueError, RecursionError) as e:
        # NaN/Infinity, a name given twice, nesting too deep for the parser.
        raise RpcError(PARSE_ERROR, f"parse error: {e}") from None


def _valid_id(value: Any) -> bool:
    if value is None or isinstance(value, str):
        return True
    # bool is an int to Python; OutOfRange and floats are not ints at all.
    return (
        isinstance(value, int)
        and not isinstance(value, bool)
        and -MAX_SAFE_INTEGER <= value <= MAX_SAFE_INTEGER
    )


def _out_of_range(params: dict[str, Any] | list[Any]) -> list[dict[str, Any]]:
    """Where `params` holds an OutOfRange number, as pydantic-style error entries.

    Iterative: a value nested as deep as the parser allows must not recurse here.
    """
    found: list[dict[str, Any]] = []
    stack: list[tuple[list[str | int], Any]] = [([], params)]
    while stack:
        loc, value = stack.pop()
        if isinstance(value, OutOfRange):
            message = (
                f"number {value.text} out of range: integers must be within "
                f"+-{MAX_SAFE_INTEGER}, floats finite"
            )
            found.append({"loc": loc, "msg": message, "type": "number_out_of_range"})
        elif isinstance(value, dict):
            stack.extend(([*loc, key], item) for key, item in value.items())
        elif isinstance(value, list):
            stack.extend(([*loc, index], item) for index, item in enumerate(value))
    found.sort(key=lambda error: [str(part) for part in error["loc"]])
    return found


@dataclass(frozen=True, slots=True)
class _Request:
    method: str
    params: dict[str, Any] | list[Any] | None
    id: Id
    notification: bool


def _check_request(obj: Any) -> _Request:
    """The JSON-RPC 2.0 shape of one request, or RpcError(-32600) carrying the id if readable."""
    if not isinstance(obj, dict):
        raise RpcError(INVALID_REQUEST, "invalid request: expected a JSON object")
    raw_id = obj.get("id")
    id: Id = raw_id if _valid_id(raw_id) else None
    if obj.get("jsonrpc") != "2.0":
        raise _InvalidRequest('invalid request: "jsonrpc" must be "2.0"', id)
    if not _valid_id(raw_id):
        raise _InvalidRequest(
            f'invalid request: "id" must be a string, an integer within +-{MAX_SAFE_INTEGER}'
            " or null",
            None,
        )
    method = obj.get("method")
    if not isinstance(method, str):
        raise _InvalidRequest('invalid request: "method" must be a string', id)
    params = obj.get("params")
    if params is not None and not isinstance(params, dict | list):
        raise _InvalidRequest('invalid request: "params" must be an object or an array', id)
    return _Request(method, params, id, notification="id" not in obj)


class _InvalidRequest(RpcError):
    """-32600 with the request's id, when it could be read."""

    def __init__(self, message: str, id: Id) -> None:
        super().__init__(INVALID_REQUEST, message)
        self.id = id


def _describe(errors: list[Any]) -> str:
    parts = []
    for error in errors:
        where = ".".join(str(part) for part in error["loc"]) or "params"
        parts.append(f"{where}: {error['msg']}")
    return "invalid params: " + "; ".join(parts)


def _bind_params(name: str, method: Method, params: dict[str, Any] | list[Any] | None) -> Any:
    """The handler's arguments: () or (model,), or RpcError(-32602)."""
    empty = params is None or params == [] or params == {}
    if method.params_model is None:
        if not empty:
            raise RpcError(INVALID_PARAMS, f"invalid params: {name} takes no params")
        return ()
    if isinstance(params, list) and params:
        raise RpcError(INVALID_PARAMS, "invalid params: params must be an object (by name)")
    if params and (beyond := _out_of_range(params)):
        raise RpcError(INVALID_PARAMS, _describe(beyond), beyond)
    try:
        return (method.params_model.model_validate(params or {}),)
    except ValidationError as e:
        errors = e.errors(include_url=False, include_context=False, include_input=False)
        data = [{"loc": list(err["loc"]), "msg": err["msg"], "type": err["type"]} for err in errors]
        raise RpcError(INVALID_PARAMS, _describe(data), data) from None


def _as_rpc_error(exc: Exception) -> RpcError | None:
    """RpcError itself, or any exception that carries an integer code and a string message."""
    if isinstance(exc, RpcError):
        return exc
    code = getattr(exc, "code", None)
    message = getattr(exc, "message", None)
    if isinstance(code, int) and not isinstance(code, bool) and isinstance(message, str):
        return RpcError(code, message, getattr(exc, "data", None))
    return None


# --- dispatch ---------------------------------------------------------------


async def _call(request: _Request, methods: Mapping[str, Method], context: object) -> bytes | None:
    """Run one valid request; its encoded response, or None for a notification."""
    try:
        method = methods.get(request.method)
        if method is None:
            raise RpcError(METHOD_NOT_FOUND, f"method not found: {request.method}")
        args = _bind_params(request.method, method, request.params)
    except Exception as exc:
        return _failed(exc, request.method, request.id, request.notification)
    return await _run(method, args, request.method, request.id, request.notification, context)


async def call_bound(
    method: Method, args: tuple[Any, ...], name: str, id: Id, context: object
) -> bytes:
    """A request whose parameters the caller has already bound: run it, its response.

    For the realtime fast path (fastpath.py), which reads a realtime request
    of one exact shape itself; everything after the reading is `_call`'s.
    """
    answer = await _run(method, args, name, id, False, context)
    assert answer is not None  # not a notification
    return answer


async def _run(
    method: Method,
    args: tuple[Any, ...],
    name: str,
    id: Id,
    notification: bool,
    context: object,
) -> bytes | None:
    try:
        token = _context.set(context)
        try:
            result = await method.handler(*args)
        finally:
            _context.reset(token)
    except Exception as exc:
        return _failed(exc, name, id, notification)
    if notification:
        return None
    return _encode_result(result, id, name)


def _failed(exc: Exception, name: str, id: Id, notification: bool) -> bytes | None:
    error = _as_rpc_error(exc)
    if error is None:
        log.exception("internal error", method=name, id=id)
        error = RpcError(INTERNAL_ERROR, "internal error")
    if notification:
        log.debug("notification failed", method=name, code=error.code)
        return None
    return _encode_failure(error, id, name)


async def _one(obj: Any, methods: Mapping[str, Method], context: object) -> bytes | None:
    try:
        request = _check_request(obj)
    except _InvalidRequest as e:
        return encode_error(e.code, e.message, e.id)
    except RpcError as e:
        return encode_error(e.code, e.message, None)
    return await _call(request, methods, context)


@dataclass(frozen=True, slots=True)
class Incoming:
    """One request line, parsed once: what `answer` will run, and how much of it.

    `requests` is what the line costs against a client's limit on requests
    in flight: a batch's length, else 1. When `reply` is set the line is
    answered with it as it is and nothing runs (`requests` is 0): it is not
    JSON, or a batch that is empty or over the cap.
    """

    message: Any
    requests: int
    reply: bytes | None = None


def decode(line: bytes, max_batch: int = MAX_BATCH) -> Incoming:
    """Parse one line (with or without its newline). Never raises for what a client sent."""
    try:
        message = _parse(line)
    except RpcError as e:
        return Incoming(None, 0, encode_error(e.code, e.message, None))
    if not isinstance(message, list):
        return Incoming(message, 1)
    if not message:
        return Incoming(None, 0, encode_error(INVALID_REQUEST, "invalid request: empty batch"))
    if len(message) > max_batch:
        error = f"invalid request: batch over {max_batch} requests"
        return Incoming(None, 0, encode_error(INVALID_REQUEST, error))
    return Incoming(message, len(message))


def is_immediate(incoming: Incoming, methods: Mapping[str, Method]) -> bool:
    """A single request for a method that never suspends: answerable without a task."""
    message = incoming.message
    if incoming.reply is not None or not isinstance(message, dict):
        return False
    name = message.get("method")
    method = methods.get(name) if isinstance(name, str) else None
    return method is not None and method.immediate


async def answer(
    incoming: Incoming, methods: Mapping[str, Method], context: object
) -> bytes | None:
    """Run a decoded line: the response (single or batch array) as bytes without a newline,
    or None when nothing is to be sent (a notification, a batch of only notifications).

    Never raises for anything the client sent or a handler did; cancellation passes through.
    Batch elements run concurrently; the array is sent once all of them are done.
    """
    if incoming.reply is not None:
        return incoming.reply
    message = incoming.message
    if not isinstance(message, list):
        return await _one(message, methods, context)
    async with asyncio.TaskGroup() as tg:
        tasks = [tg.create_task(_one(element, methods, context)) for element in message]
    answers = [answer for task in tasks if (answer := task.result()) is not None]
    if not answers:
        return None
    return b"[" + b",".join(answers) + b"]"


async def dispatch(
    line: bytes, methods: Mapping[str, Method], context: object, max_batch: int = MAX_BATCH
) -> bytes | None:
    """`decode` then `answer`: one line in, its response (or None) out."""
    return await answer(decode(line, max_batch), methods, context)
