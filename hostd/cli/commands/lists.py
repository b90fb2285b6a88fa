"""Tables: jobs and faults."""

from __future__ import annotations

import argparse
from typing import Any

from hostd.cli import render
from hostd.cli.client import Client
from hostd.cli.commands.base import (
    OK,
    CliError,
    listing,
)
from hostd.cli.render import Output

# -- lists ---------------------------------------------------------------------------


async def jobs(c: Client, args: argparse.Namespace, out: Output) -> int:
    params: dict[str, Any] = {"limit": args.limit}
    named = {m for m in (args.machine_arg, args.machine) if m is not None}
    if len(named) > 1:
        raise CliError(f"two machines named: {args.machine_arg} and --machine {args.machine}")
    if named:
        params["machine"] = named.pop()
    listing(out, await c.call("job.list", **params), render.jobs, "no jobs")
    return OK


async def faults(c: Client, args: argparse.Namespace, out: Output) -> int:
    """The active faults (fault.list answers the whole table; --all shows it); first,
    one cleared (--clear: fault.clear) or its override set or removed (--override,
    --remove-override: fault.override), where the fault table allows it."""
    machine = args.machine
    if args.clear is not None:
        await c.call("fault.clear", machine=machine, fault=args.clear)
    elif args.override is not None:
        await c.call("fault.override", machine=machine, fault=args.override, override=True)
    elif args.remove_override is not None:
        await c.call("fault.override", machine=machine, fault=args.remove_override, override=False)
    rows = await c.call("fault.list", machine=machine)
    if not args.all:
        rows = [row for row in rows if row.get("active")]
    listing(out, rows, render.faults, f"{args.machine}: no active faults")
    return OK
