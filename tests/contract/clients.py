"""A client written from api.md alone, over either transport: the Unix socket or /api.

Both speak plain JSON-RPC 2.0 and keep every message as it came: answers
by id, answers without an id (a parse error, an invalid request), and
notifications, in order.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
from typing import Any

import aiohttp

TIMEOUT = 15.0


class ContractClient:
    """The transport-neutral part: ids, waiting answers, queued notifications."""

    def __init__(self) -> None:
        self._ids = itertools.count(1)
        self._waiting: dict[int, asyncio.Future[dict[str, Any]]] = {}
        self.notifications: asyncio.Queue[dict[str, Any]] = asyncio.Queue()
        self.unmatched: asyncio.Queue[dict[str, Any]] = asyncio.Queue()  # answers, id null

    async def _send(self, text: str) -> None:
        raise NotImplementedError

    def _received(self, text: str | bytes) -> None:
        msg = json.loads(text)
        if isinstance(msg, dict) and msg.get("id") in self._waiting:
            self._waiting.pop(msg["id"]).set_result(msg)
        elif isinstance(msg, dict) and "method" in msg:
            self.notifications.put_nowait(msg)
        else:
            self.unmatched.put_nowait(msg)

    async def request(self, method: str, params: dict[str, Any] | None = None) -> dict[str, Any]:
        """The whole answer message (result or error) to one request."""
        msg_id = next(self._ids)
        future: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
        self._waiting[msg_id] = future
        message: dict[str, Any] = {"jsonrpc": "2.0", "id": msg_id, "method": method}
        if params is not None:
            message["params"] = params
        await self._send(json.dumps(message))
        async with asyncio.timeout(TIMEOUT):
            return await future

    async def raw(self, text: str) -> dict[str, Any]:
        """Send one message as it is; the answer that matched no request (id null)."""
        await self._send(text)
        async with asyncio.timeout(TIMEOUT):
            answer: dict[str, Any] = await self.unmatched.get()
        return answer

    async def close(self) -> None:
        raise NotImplementedError


class SocketClient(ContractClient):
    """Newline-delimited JSON over the Unix socket."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        super().__init__()
        self._writer = writer
        self._task = asyncio.create_task(self._read(reader))

    @classmethod
    async def open(cls, path: str) -> SocketClient:
        reader, writer = await asyncio.open_unix_connection(path, limit=8 * 1024 * 1024)
        return cls(reader, writer)

    async def _read(self, reader: asyncio.StreamReader) -> None:
        while line := await reader.readline():
            self._received(line)

    async def _send(self, text: str) -> None:
        self._writer.write(text.encode() + b"\n")
        await self._writer.drain()

    async def close(self) -> None:
        self._task.cancel()
        self._writer.close()
        with contextlib.suppress(Exception):
            await self._writer.wait_closed()


class WebSocketClient(ContractClient):
    """One JSON-RPC message a text frame over the web server's /api."""

    def __init__(self, ws: aiohttp.ClientWebSocketResponse) -> None:
        super().__init__()
        self._ws = ws
        self._task = asyncio.create_task(self._read())

    async def _read(self) -> None:
        async for message in self._ws:
            self._received(message.data)

    async def _send(self, text: str) -> None:
        await self._ws.send_str(text)

    async def close(self) -> None:
        await self._ws.close()
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task
