"""The realtime fast path: a lone realtime request answered as soon as its bytes are read.

Why: a `!` must reach the board within 1 ms at p99, with a job streaming and
other clients flooding the daemon with queries (docs/performance.md, P2 and
P2f). A request that goes the usual way (`ApiServer._read_loop`) waits for
the client's reader task to be scheduled, a loop pass after its bytes
arrived, and then for a task of its own: under a flood, that loop pass is
most of the millisecond. The fast path skips both waits.

Which methods: those registered with `immediate=True` (`rpc.Methods.register`),
handlers that write a realtime byte and never suspend. `methods.build_methods`
marks machine.feedhold, machine.cycle_start, machine.queue_flush,
machine.job_kill, machine.jog_stop, machine.override and machine.safety_door.
Only a single request takes the fast path (`rpc.is_immediate`): a batch or a
line that is not a request goes the usual way, whatever names it holds.

Two ways, the first one faster:

- In the read callback: the connection's protocol (`Connection`) hands every
  chunk the socket delivers to `FastPath`, which answers it on the spot when
  it is exactly one whole line naming such a method, not over the line
  limit. The handler runs to its end right there (`_run_now`), and the `!` is
  written in the very callback that read the request. A request of the usual
  shape for a method that takes only a machine (`Shape`) is read there by a
  regular expression, not the JSON parser, and its params are validated
  once a machine, not once a request: on a busy daemon the parser and the
  model were most of the time from the request's bytes to the `!`.
- In the reader task (`intake.Intake`, every transport's): any other lone
  request for such a method that the reader task has read runs in that
  task, not in a task of its own.

Order: a request on the fast path never overtakes an earlier request of the
same client. Either way is taken only while none of the client's earlier
requests is under way or waiting to start (the reader task's `pending` is
empty): a feedhold must not run before the job.resume sent ahead of it. The
callback also needs the client to have nothing unread (no bytes in its
StreamReader, none its LineReader has not yet returned as a line), since
those would be requests sent before this one, and the connection not to be
closed. Anything else reaches the reader task as usual.

The WebSocket transport (web/websocket.py) has no read callback of its own to hook:
it has only the reader-task way, under the same rule (the same `Intake`).
"""

from __future__ import annotations

import asyncio
import re
from collections.abc import Callable, Collection, Mapping
from typing import TYPE_CHECKING, Any, cast

from pydantic import BaseModel, ValidationError

from hostd.api import rpc
from hostd.api.lines import LineReader

if TYPE_CHECKING:
    from hostd.api.client import Client


class FastPath:
    """The realtime methods of one server's table, and when a client's request may skip ahead.

    `max_line` and `max_batch` are the server's: a line over the limit is left
    to the reader task, which refuses it.
    """

    def __init__(self, methods: Mapping[str, rpc.Method], *, max_line: int, max_batch: int) -> None:
        self._methods = methods
        self._max_line = max_line
        self._max_batch = max_batch
        # The methods' names as they stand in a request line (quoted), as bytes: a chunk
        # naming none of them is passed on without being decoded.
        self._names = [f'"{name}"'.encode() for name, m in methods.items() if m.immediate]
        # Those that take only a machine (feedhold, cycle_start...): read by `Shape`. Imported
        # here: the methods' package imports the server, which imports this module.
        from hostd.api.methods.params import MachineParams

        self._params = MachineParams
        # Each machine's params, validated once (frozen, so one serves every request): a
        # model's construction costs about as much as the rest of the read, cold.
        self._bound: dict[str, tuple[MachineParams]] = {}
        self._shape = Shape(
            {
                name: m
                for name, m in methods.items()
                if m.immediate and m.params_model is MachineParams
            }
        )

    def attach(
        self,
        transport: asyncio.BaseTransport,
        client: Client,
        reader: asyncio.StreamReader,
        lines: LineReader,
        pending: Collection[object],
    ) -> None:
        """Answer `client`'s realtime requests in its read callback from now on.

        `pending` is the reader task's set of the client's requests under way;
        the callback takes nothing while it holds any. A transport whose
        protocol is not a `Connection` has no callback to hook: nothing changes.
        """
        connection = transport.get_protocol()
        if isinstance(connection, Connection):
            connection.fast = lambda data: (
                not pending and self._answer_now(client, reader, lines, data)
            )

    def _answer_now(
        self, client: Client, reader: asyncio.StreamReader, lines: LineReader, data: bytes
    ) -> bool:
        """A realtime request answered as its bytes arrive, not a loop pass later; or False.

        Only a chunk that is one whole line naming a realtime method, from a
        client with nothing else unread nor under way (so nothing it sent
        before is overtaken): the `!` of a client beside a query flood is
        written in the very callback that read it.
        """
        if client.closed or len(data) > self._max_line or lines.pending or _unread(reader):
            return False
        read = self._shape.read(data)
        args = None if read is None else self._machine_params(read[2])
        if read is not None and args is not None:
            method, name, _, id = read
            response = _run_now(rpc.call_bound(method, args, name, id, client))
        else:
            if (
                not data.endswith(b"\n")
                or data.count(b"\n") != 1
                or not any(name in data for name in self._names)
            ):
                return False
            incoming = rpc.decode(data[:-1], max_batch=self._max_batch)
            if not rpc.is_immediate(incoming, self._methods):
                return False
            response = _run_now(rpc.answer(incoming, self._methods, client))
        if response is not None:
            client.send_line(response)
        return True

    def _machine_params(self, machine: str) -> tuple[BaseModel] | None:
        """The handler's arguments for `machine`, validated the first time; None if invalid
        (never, for what `Shape` reads: its pattern is MachineId's)."""
        args = self._bound.get(machine)
        if args is None:
            try:
                args = (self._params.model_validate({"machine": machine}),)
            except ValidationError:
                return None
            if len(self._bound) >= _BOUND:
                self._bound.clear()  # a client naming ever new machines gets no unbounded cache
            self._bound[machine] = args
        return args


_BOUND = 1024

# One member of a request object, as the shape reads it: a key, and a value that is a
# string of id characters, an integer, or a params object naming only a machine. JSON's
# whitespace but the newline (a request is one line); no escapes (the strings are read
# as they stand, so their bytes are their value).
_WS = rb"[ \t\r]*"
_MEMBER = (
    rb'("(?:jsonrpc|id|method|params)")' + _WS + rb":" + _WS + rb"("
    rb'"[A-Za-z0-9_.-]{0,64}"'
    rb"|-?(?:0|[1-9][0-9]{0,14})"
    rb"|\{" + _WS + rb'"machine"' + _WS + rb":" + _WS + rb'"[A-Za-z0-9_.-]{1,64}"' + _WS + rb"\})"
)
# No two of its repeats side by side, nor nested: it runs in time linear in the line.
_REQUEST = re.compile(
    _WS + rb"\{" + _WS + (_WS + rb"," + _WS).join([_MEMBER] * 4) + _WS + rb"\}" + _WS + rb"\n"
)
_KEYS = frozenset((b'"jsonrpc"', b'"id"', b'"method"', b'"params"'))


class Shape:
    """A realtime request of one exact shape, read without the JSON parser.

    Why: on a busy daemon the fast path runs with its code and data out of the
    CPU's caches (the job's lines and the fan-out evicted them), and there the
    JSON decoder, the request checks and the params model cost about 130 us
    of the 200 from the request's read to the Machine (docs/performance-log.md,
    "The realtime path under load"). This regular expression, and the params
    validated once a machine (`FastPath`), bring the 200 to about 65.

    The shape: one JSON object on one line with exactly the four members
    "jsonrpc": "2.0", "id" (an integer of at most 15 digits or a string of
    `[A-Za-z0-9_.-]`), "method" naming one of `methods` (immediate methods
    whose params are `MachineParams`), and "params": {"machine": id}, in any
    order, with JSON's blanks but the newline. Every request it reads is valid, and
    reads as the parser and `MachineParams` would read it (the id pattern and
    length are MachineId's); anything else, however valid, is None here and
    goes the general way.
    """

    def __init__(self, methods: Mapping[str, rpc.Method]) -> None:
        self._methods = {f'"{name}"'.encode(): (name, m) for name, m in methods.items()}

    def read(self, data: bytes) -> tuple[rpc.Method, str, str, int | str] | None:
        """(method, its name, the machine, the request's id), or None."""
        if not self._methods:
            return None
        found = _REQUEST.fullmatch(data)
        if found is None:
            return None
        k0, v0, k1, v1, k2, v2, k3, v3 = found.groups()
        members = {k0: v0, k1: v1, k2: v2, k3: v3}
        if members.keys() != _KEYS or members[b'"jsonrpc"'] != b'"2.0"':
            return None
        method = self._methods.get(members[b'"method"'])
        params = members[b'"params"']
        raw_id = members[b'"id"']
        if method is None or params[:1] != b"{" or raw_id[:1] == b"{":
            return None
        machine = params.split(b'"')[3].decode()
        id = raw_id[1:-1].decode() if raw_id[:1] == b'"' else int(raw_id)
        return method[1], method[0], machine, id


class Connection(asyncio.StreamReaderProtocol):
    """A client's connection: a stream, and a fast path for realtime requests (`fast`).

    `fast` is offered every chunk read before the stream is; when it returns
    True it has answered the chunk and the stream never sees it.
    """

    def __init__(
        self,
        reader: asyncio.StreamReader,
        connected: Callable[[asyncio.StreamReader, asyncio.StreamWriter], Any],
    ) -> None:
        super().__init__(reader, connected)
        self.fast: Callable[[bytes], bool] | None = None

    def data_received(self, data: bytes) -> None:
        fast = self.fast
        if fast is None or not fast(data):
            super().data_received(data)


def _unread(reader: asyncio.StreamReader) -> bool:
    """Bytes the reader holds that its task has not taken yet (asyncio keeps them in _buffer)."""
    return bool(getattr(reader, "_buffer", b"x"))


def _run_now(coroutine: Any) -> bytes | None:
    """Run a coroutine that never suspends (an immediate method's answer) to its end, here."""
    try:
        coroutine.send(None)
    except StopIteration as done:
        return cast(bytes | None, done.value)
    coroutine.close()
    raise RuntimeError("an immediate method suspended")
