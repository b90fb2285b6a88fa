"""What every command shares: exit statuses, the client-side error, and following a
started job to its end."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Final

from rich.console import Console

from hostd.cli import render
from hostd.cli.client import Client
from hostd.cli.interactive import CtrlC, StdinLines
from hostd.cli.progress import Detached, JobFollower
from hostd.cli.render import Output

OK: Final = 0
FAILED: Final = 1
USAGE: Final = 2
INTERRUPTED: Final = 130


class CliError(Exception):
    """A problem on the client's side (a file that cannot be read): exit `status`."""

    def __init__(self, message: str, status: int = USAGE) -> None:
        super().__init__(message)
        self.message = message
        self.status = status


async def follow_job(c: Client, machine: str, job_id: int, out: Output) -> int:
    """Follow a started job to its end (Ctrl-C asks, as in `run`); 0 if it completed."""
    with CtrlC() as ctrl_c:
        out.message(f"job #{job_id} started on {machine}")
        follower = JobFollower(
            c, machine, job_id, console=out.err, ctrl_c=ctrl_c, answers=StdinLines()
        )
        try:
            job = await follower.follow()
        except Detached:
            out.message(f"stopped following job #{job_id}; it goes on (hostd cancel {machine})")
            return INTERRUPTED
    return outcome(out, job, job_id)


def outcome(out: Output, job: dict[str, Any], job_id: int) -> int:
    """A followed job's end: its row (or JSON), and OK only when it completed."""
    if out.json:
        out.print_json(job)
    else:
        render.jobs(out.out, [job])
    if job.get("state") == "completed":
        return OK
    error = job.get("error")
    why = f": {render.job_error(job)}" if isinstance(error, dict) else ""
    out.message(f"hostd: job #{job_id} {job.get('state')}{why}")
    return FAILED


def listing(
    out: Output,
    rows: list[dict[str, Any]],
    show: Callable[[Console, Sequence[dict[str, Any]]], None],
    empty: str,
) -> None:
    """A list result: raw JSON, or a table, or (on stderr) a note that there is nothing."""
    if out.json:
        out.print_json(rows)
    elif not rows:
        out.message(empty)
    else:
        show(out.out, rows)
