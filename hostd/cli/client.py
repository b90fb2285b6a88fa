"""A small asyncio JSON-RPC 2.0 client for the daemon's Unix socket.

The CLI's only way to talk to hostd, and usable from scripts and tests:

    async with Client(path) as c:
        info = await c.call("daemon.info")
        await c.call("subscribe", topics=["status"], machine="laser1")
        async for note in c.notifications():
            ...

Framing is api.md's: one JSON value per line. Requests may be pipelined
(several `call`s awaited concurrently on one connection); each response is
matched to its call by `id`, so the order the daemon answers in does not
matter. Notifications (messages without an `id`) go to a bounded queue that
`notifications()` iterates.

The notification queue drops its *oldest* entry when full rather than
blocking the reader: a blocked reader would also stop delivering responses,
so a slow consumer would hang its own calls. Every topic of api.md carries
whole objects (a snapshot, a job row), so a consumer that falls behind
loses history, never the latest state. `dropped` counts what was lost.

This module deliberately imports nothing from the server side: a client
must not need the daemon's dependencies to start.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import json
from collections.abc import AsyncIterator
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Final, Self

DEFAULT_SOCKET: Final = "/run/hostd/hostd.sock"
SOCKET_ENV: Final = "HOSTD_SOCKET"

# Responses such as a long job.list are one line each; asyncio's 64 KiB default is too small.
LINE_LIMIT: Final = 16 * 1024 * 1024
NOTIFICATION_BACKLOG: Final = 10_000


class ClientError(Exception):
    """Base of everything this module raises; `str()` is meant for the user."""


class RpcError(ClientError):
    """The daemon answered a call with a JSON-RPC error (api.md's codes)."""

    def __init__(self, code: int, message: str, data: Any = None) -> None:
        super().__init__(f"{message} ({code})")
        self.code = code
        self.message = message
        self.data = data


class CannotConnect(ClientError):
    """Nothing (or nothing we may use) listens at the socket path."""


class ConnectionLost(ClientError):
    """The daemon closed the connection, or sent something that is not JSON-RPC."""


@dataclass(frozen=True, slots=True)
class Notification:
    """One server-to-client message without an `id`: a subscription topic."""

    method: str
    params: dict[str, Any]


class _Closed:
    """End-of-stream marker in the notification queue, carrying why it ended."""

    def __init__(self, reason: str) -> None:
        self.reason = reason


def connect_error(path: str, exc: OSError) -> CannotConnect:
    """The message a user sees when the socket cannot be reached, with a hint at the cause."""
    why = exc.strerror or str(exc)
    if exc.errno in (errno.EACCES, errno.EPERM):
        hint = "is your user allowed to use it (the socket's group)?"
    else:
        hint = "is the daemon running?"
    return CannotConnect(f"cannot reach hostd at {path}: {why}; {hint}")


class Client:
    """One connection to the daemon. Use as an async context manager.

    The reader task is owned by the client: started on enter, cancelled and
    awaited on exit, so nothing outlives the `async with` block.
    """

    def __init__(self, path: str, *, backlog: int = NOTIFICATION_BACKLOG) -> None:
        self.path = path
        self.dropped = 0
        self._next_id = 1
        self._pending: dict[int, asyncio.Future[Any]] = {}
        self._notes: asyncio.Queue[Notification | _Closed] = asyncio.Queue(backlog)
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._task: asyncio.Task[None] | None = None
        self._closed: str | None = None  # why the connection ended, once it has
        self._farewell: str | None = None  # an error the daemon sent without an id

    async def __aenter__(self) -> Self:
        try:
            self._reader, self._writer = await asyncio.open_unix_connection(
                self.path, limit=LINE_LIMIT
            )
        except OSError as exc:
            raise connect_error(self.path, exc) from None
        self._task = asyncio.create_task(self._read_loop(), name="hostd-client-reader")
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    async def close(self) -> None:
        """Hang up; calls still waiting fail with ConnectionLost."""
        self._shut("connection closed by the client")
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        if self._writer is not None:
            self._writer.close()
            with contextlib.suppress(OSError):
                await self._writer.wait_closed()
            self._writer = None

    # -- calls -------------------------------------------------------------

    async def call(self, method: str, /, **params: Any) -> Any:
        """Call `method` with named params; the result, or RpcError with the daemon's code."""
        if self._closed is not None:
            raise ConnectionLost(self._closed)
        if self._writer is None:
            raise ClientError("the client is not connected (use `async with Client(...)`)")
        request_id = self._next_id
        self._next_id += 1
        request: dict[str, Any] = {"jsonrpc": "2.0", "method": method, "id": request_id}
        if params:
            request["params"] = params
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._pending[request_id] = future
        try:
            line = json.dumps(request, separators=(",", ":"), ensure_ascii=False) + "\n"
            self._writer.write(line.encode())
            try:
                await self._writer.drain()
            except OSError as exc:
                raise ConnectionLost(f"hostd at {self.path} went away: {exc}") from None
            return await future
        finally:
            self._pending.pop(request_id, None)
            if future.done() and not future.cancelled():
                future.exception()  # retrieved: a failed drain may have left it unread

    # -- notifications -----------------------------------------------------

    def notifications(self) -> _Notifications:
        """Iterate notifications as they arrive; raises ConnectionLost when the daemon hangs up.

        The iterator is safe to wrap in `asyncio.timeout()`: a cancelled wait
        loses nothing and the next `anext()` carries on.
        """
        return _Notifications(self._notes)

    # -- the reader --------------------------------------------------------

    async def _read_loop(self) -> None:
        assert self._reader is not None
        reason = f"hostd at {self.path} closed the connection"
        try:
            while True:
                try:
                    line = await self._reader.readline()
                except (OSError, ValueError) as exc:  # ValueError: a line over LINE_LIMIT
                    reason = f"reading from hostd at {self.path}: {exc}"
                    break
                if not line:
                    if self._farewell is not None:
                        reason = f"{reason}: {self._farewell}"
                    break
                if not line.strip():
                    continue
                try:
                    message = json.loads(line)
                except ValueError:
                    reason = f"hostd at {self.path} sent a line that is not JSON"
                    break
                for one in message if isinstance(message, list) else [message]:
                    self._route(one)
        finally:
            self._shut(reason)

    def _route(self, message: Any) -> None:
        """A response resolves its call; a message without an id is a notification."""
        if not isinstance(message, dict):
            return
        if "id" not in message:
            method = message.get("method")
            params = message.get("params")
            if isinstance(method, str):
                self._notify(Notification(method, params if isinstance(params, dict) else {}))
            return
        error = message.get("error")
        request_id = message.get("id")
        if request_id is None and isinstance(error, dict):
            # The daemon could not read our id (a line over its size limit) or will not
            # serve us (it is full): every waiting call is a candidate, and it closes the
            # connection next anyway. With none waiting, it is why the connection ends.
            failure = _rpc_error(error)
            self._farewell = failure.message
            for waiting in self._pending.values():
                if not waiting.done():
                    waiting.set_exception(failure)
            return
        future = self._pending.get(request_id) if isinstance(request_id, int) else None
        if future is None or future.done():
            return
        if isinstance(error, dict):
            future.set_exception(_rpc_error(error))
        else:
            future.set_result(message.get("result"))

    def _notify(self, item: Notification | _Closed) -> None:
        if self._notes.full():
            self._notes.get_nowait()
            self.dropped += 1
        self._notes.put_nowait(item)

    def _shut(self, reason: str) -> None:
        """Fail every waiting call and end the notification stream, once."""
        if self._closed is not None:
            return
        self._closed = reason
        for future in self._pending.values():
            if not future.done():
                future.set_exception(ConnectionLost(reason))
        self._notify(_Closed(reason))


class _Notifications(AsyncIterator[Notification]):
    """A plain `__anext__` over the queue (not an async generator, so cancellation-safe)."""

    def __init__(self, queue: asyncio.Queue[Notification | _Closed]) -> None:
        self._queue = queue

    def __aiter__(self) -> Self:
        return self

    async def __anext__(self) -> Notification:
        item = await self._queue.get()
        if isinstance(item, _Closed):
            self._queue.put_nowait(item)  # every later call ends the same way
            raise ConnectionLost(item.reason)
        return item


def _rpc_error(error: dict[str, Any]) -> RpcError:
    code = error.get("code")
    message = error.get("message")
    return RpcError(
        code if isinstance(code, int) else -32603,
        message if isinstance(message, str) else "error without a message",
        error.get("data"),
    )
