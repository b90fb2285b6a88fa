"""Split each `!` sample of a bench run into its legs (the stamps of bench/rttrace.py).

    HOSTD_RTTRACE_DIR=/tmp/rt python -m bench --quick --only p2,p6,p7 --keep \\
        --daemon-module bench.rttrace
    python -m bench.rtsplit WORKDIR /tmp/rt

For every `*-samples.json` of the work directory (the client's write of each
feedhold and the board's read of its `!`), each sample is matched with the
first stamps of the daemons' traces after its write, and split:

- client write -> daemon read: the daemon's loop reaching the request (a
  pass of other work, or waiting for a CPU);
- read -> Machine: the request read and dispatched;
- Machine -> `!` written: the Machine, the engine, the session, the link;
- written -> board read: the kernel's pty and the board's process;
- and, beside them, written -> callback done: what the daemon did after the
  write in the same callback (the job's state published, and the like).

Printed as p50/p90/p99/max in microseconds (p99 as the bench takes it, `run.pct`).
"""

from __future__ import annotations

import bisect
import json
import sys
from pathlib import Path

from bench.run import pct

LEGS = [
    ("client write -> daemon read", None, "read"),
    ("read -> Machine", "read", "machine"),
    ("Machine -> `!` written", "machine", "written"),
    ("written -> board read", "written", None),
    ("(written -> callback done)", "written", "done"),
]


def _line(title: str, values: list[float]) -> str:
    us = [v * 1e6 for v in values]
    return (
        f"  {title:<30} p50 {pct(us, 0.5):7.0f}  p90 {pct(us, 0.9):7.0f}  "
        f"p99 {pct(us, 0.99):7.0f}  max {max(us):7.0f} us"
    )


def _after(stamps: list[float], t: float) -> float | None:
    i = bisect.bisect_left(stamps, t)
    return stamps[i] if i < len(stamps) else None


def main(argv: list[str]) -> int:
    workdir, tracedir = Path(argv[0]), Path(argv[1])
    stamps: dict[str, list[float]] = {"read": [], "machine": [], "written": [], "done": []}
    for path in tracedir.glob("rt-*.json"):
        for key, values in json.loads(path.read_text()).items():
            stamps[key].extend(values)
    for values in stamps.values():
        values.sort()
    for path in sorted(workdir.glob("*-samples.json")):
        samples = json.loads(path.read_text())
        legs: dict[str, list[float]] = {title: [] for title, _, _ in LEGS}
        whole = []
        for sent, bang in zip(samples["sent_at"], samples["bangs"], strict=True):
            at = {"sent": sent}
            for key in stamps:
                found = _after(stamps[key], sent)
                if found is None or found > bang + (1.0 if key == "done" else 0.0):
                    break
                at[key] = found
            else:
                for title, start, end in LEGS:
                    legs[title].append((at[end] if end else bang) - at[start or "sent"])
                whole.append(bang - sent)
        if not whole:
            continue
        print(f"{path.name}: {len(whole)} of {len(samples['sent_at'])} samples matched")
        for title, values in legs.items():
            print(_line(title, values))
        print(_line("whole", whole))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
