"""`hostd watch`: the machines' status, exceptions, supervisor and job changes, live.

On a terminal: a table of the machines redrawn as notifications arrive,
with supervisor changes, exceptions and job state changes printed above
it. Elsewhere: one timestamped line per event (status reports included,
since that is what a log of the machine wants), or with `--json` every
notification as it came, one JSON object a line. Ctrl-C ends it, exit 0.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Any, Final

from rich.live import Live
from rich.table import Table

from hostd.cli import render
from hostd.cli.client import Client, Notification
from hostd.cli.interactive import CtrlC, Interrupted, unless_interrupted
from hostd.cli.render import Output

TOPICS: Final = ["status", "exception", "supervisor", "job"]


class Watcher:
    """The machines as the notifications describe them, and the line each event is worth."""

    def __init__(self, snapshots: list[dict[str, Any]]) -> None:
        self.snapshots = {s["id"]: s for s in snapshots}
        self._job_states: dict[str, Any] = {
            mid: (s.get("job") or {}).get("state") for mid, s in self.snapshots.items()
        }

    def table(self) -> Table:
        grid = Table(*render.STATUS_HEADERS, title="hostd watch (Ctrl-C to stop)")
        for snap in self.snapshots.values():
            grid.add_row(*render.status_row(snap))
        return grid

    def opening(self) -> list[str]:
        """Where each machine stands when the watch begins."""
        clock = time.strftime("%H:%M:%S")
        lines = []
        for snap in self.snapshots.values():
            machine, supervisor, state, where, job = render.status_row(snap)
            lines.append(f"{clock} {machine} now {supervisor} {state} {where} job {job}")
        return lines

    def take(self, note: Notification) -> str | None:
        """Apply one notification to the view; the line it is worth printing, if any."""
        p = note.params
        mid = str(p.get("machine"))
        snap = self.snapshots.setdefault(mid, {"id": mid})
        clock = time.strftime("%H:%M:%S")
        if note.method == "status":
            if isinstance(p.get("snapshot"), dict):
                snap.update(p["snapshot"])
            fields = [render.state_name(snap), render.position(snap.get("position"))]
            if snap.get("line") is not None:
                fields.append(f"line={snap['line']}")
            if snap.get("velocity") is not None:
                fields.append(f"vel={snap['velocity']}")
            return f"{clock} {mid} status " + " ".join(fields)
        if note.method == "supervisor":
            snap["supervisor"] = p.get("to")
            return f"{clock} {mid} supervisor {p.get('from')} -> {p.get('to')} ({p.get('event')})"
        if note.method == "exception":
            return f"{clock} {mid} exception {render.json_line(p.get('report'))}"
        if note.method == "job" and isinstance(p.get("job"), dict):
            job = p["job"]
            snap["job"] = job
            if self._job_states.get(mid) == job.get("state"):
                return None  # progress alone: the table shows it, a line per tick would flood
            self._job_states[mid] = job.get("state")
            return f"{clock} {mid} job {render.job_brief(job)}"
        return None


async def live_view(c: Client, machine: str | None, out: Output) -> int:
    """Follow one machine (or all) until Ctrl-C; 0 then."""
    params: dict[str, Any] = {"topics": TOPICS}
    if machine is not None:
        params["machine"] = machine
    # Subscribe before reading the snapshots: a change in between is then seen twice, not lost.
    await c.call("subscribe", **params)
    ids = [machine] if machine else [m["id"] for m in await c.call("machine.list")]
    snaps = await asyncio.gather(*(c.call("machine.status", machine=m) for m in ids))
    watcher = Watcher(list(snaps))
    with CtrlC() as ctrl_c:
        if out.json:
            for snap in snaps:
                out.print_json(
                    {"method": "snapshot", "params": {"machine": snap["id"], "snapshot": snap}}
                )
            await _each(
                c, ctrl_c, lambda n: out.print_json({"method": n.method, "params": n.params})
            )
        elif out.out.is_terminal:
            with Live(watcher.table(), console=out.out, refresh_per_second=8) as live:

                def redraw(note: Notification) -> None:
                    line = watcher.take(note)
                    if line is not None and note.method != "status":  # the table shows status
                        live.console.print(line, markup=False, highlight=False)
                    live.update(watcher.table())

                await _each(c, ctrl_c, redraw)
        else:
            for line in watcher.opening():
                out.out.print(line, markup=False, highlight=False, soft_wrap=True)

            def write(note: Notification) -> None:
                line = watcher.take(note)
                if line is not None:
                    out.out.print(line, markup=False, highlight=False, soft_wrap=True)

            await _each(c, ctrl_c, write)
    return 0


async def _each(c: Client, ctrl_c: CtrlC, show: Callable[[Notification], None]) -> None:
    """Hand every notification to `show` until Ctrl-C."""
    notes = c.notifications()
    while True:
        try:
            note = await unless_interrupted(notes.__anext__(), ctrl_c)
        except Interrupted:
            return
        show(note)
