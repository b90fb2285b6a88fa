"""`python -m hostd.sim --data PATH [--control PATH]`: run a simulated board until stopped.

For tests and demos that need the board in another process. It prints the
port paths once they exist, then runs until SIGINT or SIGTERM. A g2core by
default; `--grbl grbl` or `--grbl grblhal` a grbl board (one port).
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
import sys

import structlog

from hostd.sim.config import SimConfig
from hostd.sim.controller import SimController
from hostd.sim.grbl import GrblConfig, GrblSimController


def _parse(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m hostd.sim", description=__doc__)
    parser.add_argument("--data", required=True, help="symlink path of the data port")
    parser.add_argument("--control", help="symlink path of a second (control) port")
    parser.add_argument(
        "--speed-factor", type=float, default=1.0, help="moves run this much faster"
    )
    parser.add_argument("--instant", action="store_true", help="moves finish at once")
    parser.add_argument(
        "--fb",
        type=float,
        default=SimConfig.fb,
        help="firmware build to be (100.26, 101.03, 101.06...): kills, flushes, alarms "
        "and holds follow that build (docs/protocol.md, Firmware builds)",
    )
    parser.add_argument(
        "--grbl",
        choices=("grbl", "grblhal"),
        help="a grbl board of this flavour instead of a g2core (one port: no --control)",
    )
    parser.add_argument(
        "--laser", action="store_true", help="grbl: laser mode on ($32=1) at power-up"
    )
    args = parser.parse_args(argv)
    if args.grbl and args.control:
        parser.error("a grbl board has one port: --control is g2core's")
    return args


async def _serve(args: argparse.Namespace) -> None:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    if args.grbl:
        board = GrblConfig(
            flavour=args.grbl,
            speed_factor=args.speed_factor,
            instant=args.instant,
            laser_mode=args.laser,
        )
        async with GrblSimController(args.data, board) as grbl:
            print(f"data {grbl.path}", flush=True)
            await stop.wait()
        return
    config = SimConfig(speed_factor=args.speed_factor, instant=args.instant, fb=args.fb)
    async with SimController(args.data, control_path=args.control, config=config) as sim:
        print(f"data {sim.data_path}", flush=True)
        if sim.control_path is not None:
            print(f"control {sim.control_path}", flush=True)
        await stop.wait()


def main(argv: list[str] | None = None) -> int:
    args = _parse(argv)
    # stdout carries only the paths, for whoever started us; logs go to stderr.
    structlog.configure(
        logger_factory=structlog.PrintLoggerFactory(sys.stderr),
        wrapper_class=structlog.make_filtering_bound_logger(logging.INFO),
    )
    asyncio.run(_serve(args))
    return 0


if __name__ == "__main__":
    sys.exit(main())
