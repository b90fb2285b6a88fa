"""The dashboard's WebSocket, as a process: logged in with a token, reading everything it is sent.

    python -m bench.webclient --url http://127.0.0.1:PORT --token hostd_...

What the page does when it opens (hostd/web/static/app.js, `onLink`): it
connects to `/api` with its session (here the same token as a Bearer
header, which the server takes as it takes the login cookie, hostd/api/web/auth.py
`_token_id`), asks `daemon.info`, and subscribes to `status`, `supervisor`,
`fault`, `job`, `console` and `exception` for every machine, with
`job_lines: false` and `status_traffic: false` (since issue 30: a running
job's own lines and their plain answers, and the status polls and reports,
are left out of its console; before, every line written and read on every
machine was a message, two a line, and the page hid the polls itself).
The client reads every message as soon as it comes and counts them (no
JSON parsing: a page that parses slowly is its own problem, not the
daemon's); it prints `ready` once subscribed, and on `stop` (stdin) one
JSON line: `{"messages": n, "bytes": n, "closed": bool}`.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import sys
from collections.abc import Mapping

import aiohttp

TOPICS = ["status", "supervisor", "fault", "job", "console", "exception"]
# The page's traffic: app.js makes the console its own subscription (job_lines and
# status_traffic false unless its "job lines" and "status reports" boxes are ticked); one
# subscription of them all gets the same messages.
SUBSCRIBE = {"topics": TOPICS, "job_lines": False, "status_traffic": False}


async def run(url: str, token: str) -> dict[str, int | bool]:
    headers = {"Authorization": f"Bearer {token}"}
    async with (
        aiohttp.ClientSession(headers=headers) as session,
        session.ws_connect(f"{url}/api", max_msg_size=0) as ws,
    ):
        for msg_id, (method, params) in enumerate(
            [("daemon.info", {}), ("subscribe", SUBSCRIBE)], 1
        ):
            await _call(ws, msg_id, method, params)
        sys.stdout.write("ready\n")
        sys.stdout.flush()
        reader = asyncio.create_task(_read(ws))
        await asyncio.get_running_loop().run_in_executor(None, _wait_for_stop)
        if reader.done():
            return reader.result()
        reader.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await reader
        return _counts


_counts: dict[str, int | bool] = {"messages": 0, "bytes": 0, "closed": False}


async def _call(
    ws: aiohttp.ClientWebSocketResponse, msg_id: int, method: str, params: Mapping[str, object]
) -> None:
    request = {"jsonrpc": "2.0", "id": msg_id, "method": method, "params": params}
    await ws.send_str(json.dumps(request))
    while True:
        answer = json.loads((await ws.receive()).data)
        if answer.get("id") == msg_id:
            if "error" in answer:
                raise RuntimeError(f"{method}: {answer['error']}")
            return


async def _read(ws: aiohttp.ClientWebSocketResponse) -> dict[str, int | bool]:
    """Every message, counted as it comes, until the server closes."""
    messages = size = 0
    try:
        async for message in ws:
            messages += 1
            size += len(message.data)
            _counts["messages"], _counts["bytes"] = messages, size
    finally:
        _counts["messages"], _counts["bytes"] = messages, size
    _counts["closed"] = True
    return _counts


def _wait_for_stop() -> None:
    for line in sys.stdin:
        if line.strip() == "stop":
            return


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--url", required=True)
    parser.add_argument("--token", required=True)
    args = parser.parse_args()
    result = asyncio.run(run(args.url, args.token))
    sys.stdout.write(json.dumps(result) + "\n")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
