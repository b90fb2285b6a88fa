"""What the realtime path's pieces cost with the CPU's caches cold: `python -m bench.coldpath`.

Why: inside a busy daemon each stage of a `!` request (decode, checks,
params) took 5-20 times its `timeit` figure, on the CPU, not waiting
(docs/performance-log.md, "The realtime path under load"): the path runs once in
a while and everything else the daemon and the machine do evicts it. This
times each piece once after walking ~10 MB of other objects, the median of
40 such calls, beside its median hot (200 calls in a row).
"""

from __future__ import annotations

import json
import re
import sys
import time
from collections.abc import Callable
from typing import Any

from hostd.api import rpc
from hostd.api.fastpath import Shape
from hostd.api.methods.params import MachineParams

LINE = b'{"jsonrpc":"2.0","id":12,"method":"machine.feedhold","params":{"machine":"bench"}}\n'
_CLUTTER = [str(i) * 3 for i in range(400_000)]


def _cold(call: Callable[[], object], n: int = 40) -> float:
    times = []
    for _ in range(n):
        sum(len(x) for x in _CLUTTER[::3])  # the caches filled with something else
        started = time.perf_counter()
        call()
        times.append(time.perf_counter() - started)
    return sorted(times)[n // 2] * 1e6


def _hot(call: Callable[[], object], n: int = 200) -> float:
    times = []
    for _ in range(n):
        started = time.perf_counter()
        call()
        times.append(time.perf_counter() - started)
    return sorted(times)[n // 2] * 1e6


async def _feedhold(p: MachineParams) -> dict[str, Any]:
    return {}


def main() -> int:
    table = rpc.Methods()
    table.register("machine.feedhold", MachineParams, _feedhold, immediate=True)
    shape = Shape(table)
    decoder = json.JSONDecoder()
    pattern = re.compile(rb'\{"jsonrpc":"2\.0","id":(\d+),"method":"([a-z_.]+)"')
    cases: dict[str, Callable[[], object]] = {
        "rpc.decode (the general way)": lambda: rpc.decode(LINE[:-1]),
        "json.JSONDecoder, made once": lambda: decoder.decode(LINE[:-1].decode()),
        "one re match": lambda: pattern.match(LINE),
        "fastpath.Shape.read": lambda: shape.read(LINE),
        "MachineParams.model_validate": lambda: MachineParams.model_validate({"machine": "b"}),
        "MachineParams.model_construct": lambda: MachineParams.model_construct(machine="b"),
        "nothing (the timer itself)": lambda: None,
    }
    for title, call in cases.items():
        sys.stdout.write(f"{title:<32} cold {_cold(call):7.1f} us   hot {_hot(call):6.1f} us\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
