"""The daemon with its realtime path timed: `python -m bench --daemon-module bench.rttrace`.

Why: P2, P6 and P7 time a `!` from the client's write to the board's read,
which holds several waits: the daemon reading the request (its loop busy
with a pass of other work, or not on a CPU), the daemon's own handling up to
the Machine and on to the port's write, and the board reading the byte.
This wrapper stamps, for each `machine.feedhold` request (`time.monotonic()`,
one clock for every process on the host):

- `read`: the client's connection got the request's bytes (the read callback);
- `machine`: the Machine was asked (`Machine.feedhold`);
- `written`: the `!` was handed to the port (`SerialChannel._send`);
- `done`: the read callback returned (what it did after the write included).

(`HOSTD_RTTRACE_YIELD=1`, the yield after a `!` tried here first, is gone: the
daemon hands the CPU over itself, on a pty, since `Link.hand_over`.)

Each daemon writes `$HOSTD_RTTRACE_DIR/rt-<pid>.json` on a clean stop;
`python -m bench.rtsplit WORKDIR TRACEDIR` splits each sample of a run kept
with `--keep` into its legs. The stamps cost a few microseconds each.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from hostd.service import add_arguments, serve_main

STAMPS: dict[str, list[float]] = {"read": [], "machine": [], "written": [], "done": []}


def _patch() -> None:
    from hostd.api import fastpath
    from hostd.link import serial
    from hostd.machine import machine

    received = fastpath.Connection.data_received
    feedhold = machine.Machine.feedhold
    send = serial.SerialChannel._send
    read, asked, written, done = (STAMPS[k] for k in ("read", "machine", "written", "done"))

    def data_received(self: fastpath.Connection, data: bytes) -> None:
        if b'"machine.feedhold"' not in data:
            received(self, data)
            return
        read.append(time.monotonic())
        received(self, data)
        done.append(time.monotonic())

    def machine_feedhold(self: machine.Machine) -> None:
        asked.append(time.monotonic())
        feedhold(self)

    def send_bang(self: serial.SerialChannel, data: bytes) -> bool:
        if data[:1] != b"!":
            return send(self, data)
        written.append(time.monotonic())
        return send(self, data)

    fastpath.Connection.data_received = data_received  # type: ignore[method-assign]
    machine.Machine.feedhold = machine_feedhold  # type: ignore[method-assign]
    serial.SerialChannel._send = send_bang  # type: ignore[method-assign]


def main() -> int:
    parser = argparse.ArgumentParser(prog="bench.rttrace")
    add_arguments(parser)
    args = parser.parse_args()
    _patch()
    try:
        return int(serve_main(args) or 0)
    finally:
        out = Path(os.environ.get("HOSTD_RTTRACE_DIR", ".")) / f"rt-{os.getpid()}.json"
        record: dict[str, Any] = STAMPS
        out.write_text(json.dumps(record))


if __name__ == "__main__":
    sys.exit(main())
