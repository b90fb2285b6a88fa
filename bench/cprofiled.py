"""The daemon under cProfile: `python -m bench --daemon-module bench.cprofiled`.

py-spy sees only Python frames and, on uvloop, cannot tell the loop's idle
wait from its work; cProfile counts each function's own CPU time (the
profiler's clock is `time.process_time`, so time asleep in epoll is not
counted) and calls. Each daemon the bench starts writes its statistics on
a clean stop to `$HOSTD_CPROFILE_DIR/hostd-<pid>.prof` (default: the
current directory); read them with `python -m pstats`. The profiler slows
every call, so the run's own figures are not the daemon's.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import sys
import time
from pathlib import Path

from hostd.service import add_arguments, serve_main


def main() -> int:
    parser = argparse.ArgumentParser(prog="bench.cprofiled")
    add_arguments(parser)
    args = parser.parse_args()
    profiler = cProfile.Profile(time.process_time)
    try:
        return int(profiler.runcall(serve_main, args) or 0)
    finally:
        out = Path(os.environ.get("HOSTD_CPROFILE_DIR", ".")) / f"hostd-{os.getpid()}.prof"
        profiler.dump_stats(out)


if __name__ == "__main__":
    sys.exit(main())
