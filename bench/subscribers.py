"""A fleet of API subscribers in one process, reading every socket as soon as it is readable.

    python -m bench.subscribers --socket PATH --count 100 --topics status --machine bench

Each client subscribes, then the fleet prints `ready` and reads until stdin
says `stop` (or closes); then it prints one JSON line: per client, the read
time (time.monotonic(), taken right after the `recv`) of every `status`
notification whose report is `{"posx": k}`, as `[[k, t], ...]`, and counts.

Cheap on purpose, so that the fleet's own cost is small next to what is
measured: non-blocking sockets under one selector, a regex on the raw bytes
for the counter, no JSON parsing of notifications.
"""

from __future__ import annotations

import argparse
import json
import re
import selectors
import socket
import sys
import time

POSX = re.compile(rb'"method":"status".*?"report":\{"posx":(\d+)\}')


def subscribe(path: str, topics: list[str], machine: str) -> tuple[socket.socket, bytes]:
    """One client subscribed to `topics` on `machine` (every machine if it is empty)."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(10)
    sock.connect(path)
    params: dict[str, object] = {"topics": topics}
    if machine:
        params["machine"] = machine
    request = {"jsonrpc": "2.0", "id": 1, "method": "subscribe", "params": params}
    sock.sendall(json.dumps(request).encode() + b"\n")
    buf = b""
    while True:
        chunk = sock.recv(65536)
        if not chunk:
            raise ConnectionError("closed while subscribing")
        buf += chunk
        *lines, buf = buf.split(b"\n")
        answers = [m for m in map(json.loads, lines) if m.get("id") == 1]
        if answers:
            if "error" in answers[0]:
                raise RuntimeError(f"subscribe failed: {answers[0]['error']}")
            break
    sock.setblocking(False)
    return sock, buf  # and the start of what came after the answer


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--socket", required=True)
    parser.add_argument("--count", type=int, required=True)
    parser.add_argument("--topics", default="status")
    parser.add_argument("--machine", default="bench", help="empty: every machine")
    args = parser.parse_args()

    topics = args.topics.split(",")
    clients = [subscribe(args.socket, topics, args.machine) for _ in range(args.count)]
    socks = [sock for sock, _ in clients]
    bufs = [rest for _, rest in clients]
    sel = selectors.DefaultSelector()
    seen: list[list[tuple[int, float]]] = [[] for _ in socks]
    messages = [0] * len(socks)
    received = [0] * len(socks)
    closed = [False] * len(socks)
    for i, sock in enumerate(socks):
        sel.register(sock, selectors.EVENT_READ, i)
    sel.register(sys.stdin, selectors.EVENT_READ, -1)
    sys.stdout.write("ready\n")
    sys.stdout.flush()

    running = True
    while running:
        for key, _ in sel.select():
            i = key.data
            if i < 0:
                command = sys.stdin.readline()
                running = bool(command) and command.strip() != "stop"
                continue
            try:
                chunk = key.fileobj.recv(1 << 20)  # type: ignore[union-attr]
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:
                chunk = b""
            now = time.monotonic()
            if not chunk:
                closed[i] = True
                sel.unregister(key.fileobj)
                continue
            received[i] += len(chunk)
            data = bufs[i] + chunk
            end = data.rfind(b"\n")
            if end < 0:
                bufs[i] = data
                continue
            bufs[i] = data[end + 1 :]
            complete = data[: end + 1]
            messages[i] += complete.count(b"\n")
            for match in POSX.finditer(complete):
                seen[i].append((int(match.group(1)), now))

    result = {
        "seen": seen,
        "messages": messages,
        "bytes": received,
        "closed": sum(closed),
    }
    sys.stdout.write(json.dumps(result) + "\n")
    sys.stdout.flush()
    for sock in socks:
        sock.close()


if __name__ == "__main__":
    main()
