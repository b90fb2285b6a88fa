"""The machine's state and one-shot actions: status, send, watch, hold/resume/clear/
reset, cancel and the tool-change answer."""

from __future__ import annotations

import argparse
import asyncio
from typing import Any, Final

from hostd.cli import render
from hostd.cli.client import Client, RpcError
from hostd.cli.commands.base import (
    OK,
    listing,
)
from hostd.cli.render import Output
from hostd.cli.watch import live_view

# -- status ------------------------------------------------------------------


async def status(c: Client, args: argparse.Namespace, out: Output) -> int:
    """One machine's snapshot, or a row per machine."""
    if args.machine is not None:
        snap = await c.call("machine.status", machine=args.machine)
        if out.json:
            out.print_json(snap)
        else:
            render.snapshot(out.out, snap)
        return OK
    listed = await c.call("machine.list")
    # Pipelined on the one connection: answers come back in whatever order they finish.
    snaps = await asyncio.gather(*(c.call("machine.status", machine=m["id"]) for m in listed))
    listing(out, list(snaps), render.machines, "no machines configured")
    return OK


# -- send ----------------------------------------------------------------------


async def send(c: Client, args: argparse.Namespace, out: Output) -> int:
    """Each line in turn, stopping at the first the daemon or the controller refuses."""
    params: dict[str, Any] = {"machine": args.machine}
    if args.timeout is not None:
        params["timeout"] = args.timeout
    for line in args.lines:
        try:
            result = await c.call("machine.send", line=line, **params)
        except RpcError as exc:
            exc.add_note(f"while sending {line!r} to {args.machine}")
            raise
        if out.json:
            out.print_json(result)
            continue
        for text in render.answer_lines(result):
            out.out.print(text, markup=False, highlight=False, soft_wrap=True)
    return OK


# -- one-shot machine and job actions ---------------------------------------------


ACTIONS: Final = {
    "hold": ("machine.feedhold", "feedhold sent"),
    "resume": ("machine.cycle_start", "cycle start sent"),
    "clear": ("machine.clear", "cleared"),
    "reset": ("machine.reset", "reset and back in sync"),
}


async def action(c: Client, args: argparse.Namespace, out: Output) -> int:
    method, done = ACTIONS[args.command]
    out.result(await c.call(method, machine=args.machine), f"{args.machine}: {done}")
    return OK


async def _job_call(c: Client, method: str, args: argparse.Namespace, out: Output) -> int:
    """A job method that answers the job's row: shown as `hostd jobs` shows one."""
    job = await c.call(method, machine=args.machine)
    if out.json:
        out.print_json(job)
    else:
        render.jobs(out.out, [job])
    return OK


async def cancel(c: Client, args: argparse.Namespace, out: Output) -> int:
    """job.cancel returns once the job has ended: show the row it ended with."""
    return await _job_call(c, "job.cancel", args, out)


async def tool_change_done(c: Client, args: argparse.Namespace, out: Output) -> int:
    """job.tool_change_done: the tool is changed; the waiting job goes on."""
    return await _job_call(c, "job.tool_change_done", args, out)


# -- watch ---------------------------------------------------------------------------


async def watch(c: Client, args: argparse.Namespace, out: Output) -> int:
    """Status, exceptions, supervisor and job changes as they come, until Ctrl-C (exit 0)."""
    return await live_view(c, args.machine, out)
