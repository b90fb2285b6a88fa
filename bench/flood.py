"""A client that floods one machine with `machine.send` queries, as fast as the daemon answers.

    python -m bench.flood --socket PATH --machine bench [--outstanding 200] [--batch 10]

It keeps `outstanding` requests unanswered: in turn a JSON-RPC batch of
`batch` requests and `batch` single request lines, each a GET (`{"sr":n}`,
`?`, `{"xvm":n}` in rotation), written as soon as answers make room. It
prints `ready` once connected, floods until stdin says `stop` (or closes),
then prints one JSON line: `{"sent": n, "answered": n, "errors": n,
"seconds": s, "error": the first error object or null}`.

Cheap on purpose, like bench/subscribers.py: the answers are counted on the
raw bytes (one `"jsonrpc"` per answer, batch or not), not parsed.
"""

from __future__ import annotations

import argparse
import itertools
import json
import re
import selectors
import socket
import sys
import time
from collections.abc import Iterator

QUERIES = ('{"sr":n}', "?", '{"xvm":n}')
ERROR = re.compile(rb'"error":(\{[^{}]*\})')


def requests(machine: str, batch: int) -> Iterator[tuple[int, bytes]]:
    """(request count, line) without end: a batch of `batch`, then `batch` single lines."""
    ids = itertools.count(1)
    lines = itertools.cycle(QUERIES)

    def one() -> dict[str, object]:
        params = {"machine": machine, "line": next(lines)}
        return {"jsonrpc": "2.0", "id": next(ids), "method": "machine.send", "params": params}

    def encode(message: object) -> bytes:
        return json.dumps(message, separators=(",", ":")).encode() + b"\n"

    while True:
        yield batch, encode([one() for _ in range(batch)])
        for _ in range(batch):
            yield 1, encode(one())


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--socket", required=True)
    parser.add_argument("--machine", required=True)
    parser.add_argument("--outstanding", type=int, default=200)
    parser.add_argument("--batch", type=int, default=10)
    args = parser.parse_args()

    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(10)
    sock.connect(args.socket)
    sel = selectors.DefaultSelector()
    sel.register(sock, selectors.EVENT_READ)
    sel.register(sys.stdin, selectors.EVENT_READ)
    source = requests(args.machine, args.batch)
    sent = answered = errors = 0
    first_error = None
    buf = b""
    sys.stdout.write("ready\n")
    sys.stdout.flush()

    t0 = time.monotonic()
    running = True
    while running:
        # Fill up to `outstanding` in one write: the answers' room is never more than that.
        out = []
        while sent - answered < args.outstanding:
            count, line = next(source)
            out.append(line)
            sent += count
        if out:
            sock.sendall(b"".join(out))
        for key, _ in sel.select():
            if key.fileobj is not sock:
                command = sys.stdin.readline()
                running = bool(command) and command.strip() != "stop"
                continue
            chunk = sock.recv(1 << 20)
            if not chunk:
                raise ConnectionError("the daemon closed the connection")
            data = buf + chunk
            end = data.rfind(b"\n") + 1
            buf, complete = data[end:], data[:end]
            answered += complete.count(b'"jsonrpc"')
            errors += complete.count(b'"error":{')
            if first_error is None and (match := ERROR.search(complete)):
                first_error = json.loads(match.group(1))
    seconds = time.monotonic() - t0

    result = {
        "sent": sent,
        "answered": answered,
        "errors": errors,
        "seconds": seconds,
        "error": first_error,
    }
    sys.stdout.write(json.dumps(result) + "\n")
    sys.stdout.flush()
    sock.close()


if __name__ == "__main__":
    main()
