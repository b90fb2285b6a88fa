"""The JSON-RPC client against a scripted server: what the daemon may do, one case each.

The scripted server is a Unix socket whose handler the test writes, so the
orders and failures a real daemon produces only sometimes (answers out of
order, a hang-up mid-call) happen every time here.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio

from hostd.cli.client import CannotConnect, Client, ConnectionLost, RpcError

Handler = Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]


class Scripted:
    """A one-handler Unix socket server; `handler` is set by each test before connecting."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.handler: Handler | None = None
        self.requests: list[dict[str, Any]] = []

    async def serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        assert self.handler is not None
        try:
            await self.handler(reader, writer)
        finally:
            writer.close()

    async def read(self, reader: asyncio.StreamReader) -> dict[str, Any]:
        request: dict[str, Any] = json.loads(await reader.readline())
        self.requests.append(request)
        return request


def send(writer: asyncio.StreamWriter, message: dict[str, Any]) -> None:
    writer.write(json.dumps({"jsonrpc": "2.0", **message}).encode() + b"\n")


@pytest_asyncio.fixture
async def server(tmp_path: Path) -> AsyncIterator[Scripted]:
    scripted = Scripted(str(tmp_path / "s.sock"))
    unix = await asyncio.start_unix_server(scripted.serve, path=scripted.path)
    async with unix:
        yield scripted


@pytest.mark.asyncio
async def test_answers_out_of_order_reach_their_own_calls(server: Scripted) -> None:
    async def handler(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        first = await server.read(reader)
        second = await server.read(reader)
        send(writer, {"id": second["id"], "result": "second"})
        send(writer, {"id": first["id"], "result": "first"})
        await writer.drain()
        await reader.read()

    server.handler = handler
    async with Client(server.path) as c:
        results = await asyncio.gather(c.call("a"), c.call("b", x=1))

    assert list(results) == ["first", "second"]
    assert [r["id"] for r in server.requests] == [1, 2]
    assert server.requests[1]["params"] == {"x": 1}
    assert "params" not in server.requests[0]


@pytest.mark.asyncio
async def test_an_error_answer_raises_with_code_message_and_data(server: Scripted) -> None:
    async def handler(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        request = await server.read(reader)
        error = {"code": 1005, "message": "controller answered 131", "data": {"status": 131}}
        send(writer, {"id": request["id"], "error": error})
        await reader.read()

    server.handler = handler
    async with Client(server.path) as c:
        with pytest.raises(RpcError) as caught:
            await c.call("machine.send", machine="m", line="G99")

    assert (caught.value.code, caught.value.message) == (1005, "controller answered 131")
    assert caught.value.data == {"status": 131}


@pytest.mark.asyncio
async def test_notifications_are_queued_in_order_beside_the_answers(server: Scripted) -> None:
    async def handler(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        request = await server.read(reader)
        send(writer, {"method": "status", "params": {"machine": "m", "n": 1}})
        send(writer, {"id": request["id"], "result": {"subscription": 1}})
        send(writer, {"method": "job", "params": {"machine": "m", "n": 2}})
        await reader.read()

    server.handler = handler
    async with Client(server.path) as c:
        assert await c.call("subscribe", topics=["status", "job"]) == {"subscription": 1}
        notes = c.notifications()
        first, second = await notes.__anext__(), await notes.__anext__()

    assert (first.method, first.params["n"]) == ("status", 1)
    assert (second.method, second.params["n"]) == ("job", 2)


@pytest.mark.asyncio
async def test_a_timed_out_wait_for_a_notification_loses_nothing(server: Scripted) -> None:
    sent = asyncio.Event()

    async def handler(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await sent.wait()
        send(writer, {"method": "status", "params": {"machine": "m"}})
        await reader.read()

    server.handler = handler
    async with Client(server.path) as c:
        notes = c.notifications()
        with pytest.raises(TimeoutError):
            async with asyncio.timeout(0.05):
                await notes.__anext__()
        sent.set()
        async with asyncio.timeout(5):
            note = await notes.__anext__()

    assert note.method == "status"


@pytest.mark.asyncio
async def test_a_full_backlog_drops_the_oldest_notifications(server: Scripted) -> None:
    async def handler(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        request = await server.read(reader)
        for n in range(5):
            send(writer, {"method": "status", "params": {"n": n}})
        send(writer, {"id": request["id"], "result": {}})
        await reader.read()

    server.handler = handler
    async with Client(server.path, backlog=2) as c:
        await c.call("subscribe", topics=["status"])  # answered after all five
        notes = c.notifications()
        kept = [(await notes.__anext__()).params["n"] for _ in range(2)]

        assert kept == [3, 4]
        assert c.dropped == 3


@pytest.mark.asyncio
async def test_a_hang_up_fails_the_waiting_call_and_ends_the_notifications(
    server: Scripted,
) -> None:
    async def handler(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await server.read(reader)  # and close without answering

    server.handler = handler
    async with Client(server.path) as c:
        with pytest.raises(ConnectionLost, match="closed the connection"):
            await c.call("machine.reset", machine="m")
        with pytest.raises(ConnectionLost):
            await c.notifications().__anext__()
        with pytest.raises(ConnectionLost):
            await c.call("daemon.info")


@pytest.mark.asyncio
async def test_a_daemon_that_turns_us_away_says_why_in_the_hang_up(server: Scripted) -> None:
    async def handler(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        send(writer, {"error": {"code": -32000, "message": "daemon full"}, "id": None})
        writer.write_eof()
        await reader.read()

    server.handler = handler
    async with Client(server.path) as c:
        with pytest.raises(ConnectionLost, match=r"closed the connection: daemon full$"):
            await c.notifications().__anext__()
        with pytest.raises(ConnectionLost, match=r"closed the connection: daemon full$"):
            await c.call("daemon.info")


@pytest.mark.asyncio
async def test_a_missing_socket_says_where_and_asks_about_the_daemon(tmp_path: Path) -> None:
    path = tmp_path / "none.sock"

    with pytest.raises(CannotConnect) as caught:
        async with Client(str(path)):
            pass

    assert str(caught.value) == (
        f"cannot reach hostd at {path}: No such file or directory; is the daemon running?"
    )
