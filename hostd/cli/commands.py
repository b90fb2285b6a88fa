"""The client subcommands of `hostd`: each one coroutine over a connected `Client`.

A command returns its exit status (0 success, 1 the daemon said no or the
job did not complete) and lets `RpcError` and the connection errors
propagate: `main.py` turns those into a message on stderr and the exit
status documented there, the same way for every command.

Results go to stdout (tables, or JSON with `--json`); progress and notes
go to stderr, so `hostd --json jobs | jq` never sees a progress bar.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import json
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, BinaryIO, Final

from rich.console import Console

from hostd.cli import render
from hostd.cli.client import Client, RpcError
from hostd.cli.interactive import CtrlC, StdinLines
from hostd.cli.progress import Detached, JobFollower
from hostd.cli.render import Output
from hostd.cli.watch import live_view

OK: Final = 0
FAILED: Final = 1
USAGE: Final = 2
INTERRUPTED: Final = 130

UPLOAD_CHUNK: Final = 512 * 1024
# A chunk's JSON must stay under the daemon's 1 MiB line limit. Plain text
# grows a little when escaped (newlines become \n); a text full of control
# characters could grow sixfold, so past this size a chunk goes as base64.
MAX_TEXT_JSON: Final = 700 * 1024


class CliError(Exception):
    """A problem on the client's side (a file that cannot be read): exit `status`."""

    def __init__(self, message: str, status: int = USAGE) -> None:
        super().__init__(message)
        self.message = message
        self.status = status


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
    _listing(out, list(snaps), render.machines, "no machines configured")
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


async def cancel(c: Client, args: argparse.Namespace, out: Output) -> int:
    """job.cancel returns once the job has ended: show the row it ended with."""
    job = await c.call("job.cancel", machine=args.machine)
    if out.json:
        out.print_json(job)
    else:
        render.jobs(out.out, [job])
    return OK


async def tool_change_done(c: Client, args: argparse.Namespace, out: Output) -> int:
    """job.tool_change_done: the tool is changed; the waiting job goes on."""
    job = await c.call("job.tool_change_done", machine=args.machine)
    if out.json:
        out.print_json(job)
    else:
        render.jobs(out.out, [job])
    return OK


# -- lists ---------------------------------------------------------------------------


async def jobs(c: Client, args: argparse.Namespace, out: Output) -> int:
    params: dict[str, Any] = {"limit": args.limit}
    if args.machine is not None:
        params["machine"] = args.machine
    _listing(out, await c.call("job.list", **params), render.jobs, "no jobs")
    return OK


async def faults(c: Client, args: argparse.Namespace, out: Output) -> int:
    """The active faults (fault.list answers the whole table; --all shows it)."""
    rows = await c.call("fault.list", machine=args.machine)
    if not args.all:
        rows = [row for row in rows if row.get("active")]
    _listing(out, rows, render.faults, f"{args.machine}: no active faults")
    return OK


def _listing(
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


# -- run -----------------------------------------------------------------------------


def upload_chunks(f: BinaryIO, size: int = UPLOAD_CHUNK) -> Iterator[tuple[str, str]]:
    """(data, encoding) pieces of a file of at most `size` bytes each, in order.

    Text goes as UTF-8 (readable in traces, a third smaller than base64);
    a piece that is not UTF-8, or would escape to a JSON line over the
    daemon's limit, goes as base64. A multi-byte character is never split
    between two text pieces. An empty file is one empty piece, so the
    upload still happens.
    """
    carry = b""
    sent = False
    while True:
        block = f.read(size - len(carry))
        data = carry + block
        if not block:
            if data or not sent:
                yield _piece(data)
            return
        cut = _utf8_boundary(data)
        head, carry = data[:cut], data[cut:]
        piece = _piece(head)
        if piece[1] == "base64":  # the carried bytes are not part of a text either
            piece, carry = _piece(data, force_base64=True), b""
        sent = True
        yield piece


def _piece(data: bytes, *, force_base64: bool = False) -> tuple[str, str]:
    if not force_base64:
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError:
            pass
        else:
            if len(json.dumps(text, ensure_ascii=False).encode()) <= MAX_TEXT_JSON:
                return text, "utf-8"
    return base64.b64encode(data).decode("ascii"), "base64"


def _utf8_boundary(data: bytes) -> int:
    """Where to cut `data` so that no UTF-8 sequence is split (its length if none is)."""
    for back in range(1, min(4, len(data)) + 1):
        byte = data[-back]
        if byte & 0xC0 == 0x80:  # a continuation byte: keep looking for the lead byte
            continue
        if byte < 0x80:
            return len(data)
        need = 2 if byte < 0xE0 else 3 if byte < 0xF0 else 4
        return len(data) - back if need > back else len(data)
    return len(data)


async def upload(c: Client, path: Path, name: str) -> int:
    """Send the file in pieces; the daemon publishes it only with the last (`final`).

    The first piece opens an upload of our own (its `upload` id); each later
    one names it and the byte `offset` it starts at, so the daemon can tell
    a repeat from a gap and never mixes our bytes with anyone else's.
    """
    try:
        f = path.open("rb")
    except OSError as exc:
        raise CliError(f"cannot read {path}: {exc.strerror or exc}") from None
    size = 0
    with f:
        pieces = upload_chunks(f)
        piece: tuple[str, str] | None = next(pieces)
        params: dict[str, Any] = {}
        while piece is not None:
            following = next(pieces, None)
            data, encoding = piece
            result = await c.call(
                "file.upload",
                name=name,
                data=data,
                encoding=encoding,
                final=following is None,
                **params,
            )
            size = int(result.get("size", 0))
            if following is not None:
                params = {"upload": result["upload"], "offset": size}
            piece = following
    return size


async def run(c: Client, args: argparse.Namespace, out: Output) -> int:
    """Upload, start, follow to the end; 0 only if the job completed."""
    path = Path(args.file)
    name = args.name or path.name
    # Subscribing first checks the machine id before the upload, and means no
    # event of the job can slip by between its start and our first read.
    await c.call("subscribe", topics=["job", "status", "exception"], machine=args.machine)
    size = await upload(c, path, name)
    out.message(f"uploaded {name} ({size} bytes)")
    params: dict[str, Any] = {"machine": args.machine, "file": name}
    if args.start_line is not None:
        params["start_line"] = args.start_line
    if getattr(args, "force", False):
        params["force"] = True  # past job.start's refusals (travel, lines the board refuses)
    if getattr(args, "from_line", None) is not None:
        plan = await c.call("job.recovery", machine=args.machine, file=name, line=args.from_line)
        resume_plan(out, plan)
        if not args.yes and not await confirm(out, f"Resume at line {plan['line']}?"):
            out.message("not started")
            return FAILED
        params["start_line"] = plan["line"]
    # From here on Ctrl-C is a question about the job, not the end of the client; a
    # press in the instant the job starts is asked about as soon as it is followed.
    with CtrlC() as ctrl_c:
        started = await c.call("job.start", **params)
        job_id = int(started["job"])
        out.message(f"job #{job_id} started on {args.machine}")
        for warning in started.get("warnings") or ():  # e.g. M6 lines a policy ignores
            out.message(f"warning: {warning}")
        follower = JobFollower(
            c, args.machine, job_id, console=out.err, ctrl_c=ctrl_c, answers=StdinLines()
        )
        try:
            job = await follower.follow()
        except Detached:
            out.message(
                f"stopped following job #{job_id}; it goes on "
                f"(hostd cancel {args.machine} stops it)"
            )
            return INTERRUPTED
    return _outcome(out, job, job_id)


async def confirm(out: Output, question: str) -> bool:
    """Ask on stderr, read a line from stdin: only "y" or "yes" is a yes."""
    out.message(f"{question} [y/N]")
    answer = await StdinLines().readline()
    return (answer or "").strip().lower() in ("y", "yes")


def resume_plan(out: Output, plan: dict[str, Any]) -> None:
    """What a resume will send and what it is unsure of, before anything moves."""
    if out.json:
        out.print_json(plan)
        return
    pos = plan.get("position") or {}
    where = " ".join(f"{a.upper()}{v}" for a, v in pos.items() if v is not None)
    out.message(
        f"resume at line {plan['line']}, from {where} ({plan.get('units')}, {plan.get('wcs')})"
    )
    out.message("restore: " + " | ".join(plan.get("preamble") or []))
    out.message("approach: " + " | ".join(plan.get("approach") or []))
    for text in plan.get("uncertain") or []:
        out.message(f"uncertain: {text}")


# -- analyze -------------------------------------------------------------------------


async def analyze(c: Client, args: argparse.Namespace, out: Output) -> int:
    """Upload the file, then `file.analyze` it (with a machine's speeds and travel).

    Exits FAILED when job.start would refuse the file: lines the board would refuse
    or must not run (`problems`), or moves beyond the machine's travel.
    """
    path = Path(args.file)
    name = args.name or path.name
    await upload(c, path, name)
    params: dict[str, Any] = {"file": name}
    if args.machine is not None:
        params["machine"] = args.machine
    result = await c.call("file.analyze", **params)
    refused = bool(result.get("problems_total") or result.get("beyond_travel"))
    if out.json:
        out.print_json(result)
        return FAILED if refused else OK
    minutes, seconds = divmod(round(result["duration_s"]), 60)
    rows = [
        ("lines", str(result["lines"])),
        ("moves", f"{result['moves']} ({result['rapids']} rapid, {result['arcs']} arcs)"),
        ("units", " ".join(result["units"]) or "-"),
        ("tools", " ".join(str(t) for t in result["tools"]) or "-"),
        ("max S", str(result["max_speed"]) if result["max_speed"] is not None else "-"),
        ("estimate", f"{minutes} min {seconds:02d} s"),
    ]
    for axis, (low, high) in result["bounds"].items():
        rows.append((f"{axis} (mm)", f"{low:.3f} .. {high:.3f}"))
    render.pairs(out.out, rows)
    problems = [f"line {p['line']}: {p['text']}" for p in result.get("problems", [])]
    for text in result["warnings"]:
        # A refused M6 is also a warning (for the dashboard): say it once, as refused.
        if not any(text.startswith(problem) for problem in problems):
            out.out.print(f"warning: {text}", markup=False)
    for problem in problems:
        out.out.print(f"refused: {problem}", markup=False)
    more = result.get("problems_total", 0) - len(result.get("problems", []))
    if more > 0:
        out.out.print(f"refused: and {more} more lines", markup=False)
    if refused:
        out.message("job.start refuses this file (force starts it anyway)")
    return FAILED if refused else OK


# -- watch ---------------------------------------------------------------------------


async def watch(c: Client, args: argparse.Namespace, out: Output) -> int:
    """Status, exceptions, supervisor and job changes as they come, until Ctrl-C (exit 0)."""
    return await live_view(c, args.machine, out)


# -- the operator's day: home, zero, probe, override, spindle -------------------------------

AXIS_LETTERS: Final = "xyzabc"


def axis_letters(text: str) -> list[str]:
    """`xyz` -> ["x", "y", "z"]: each a machine axis, once (CliError otherwise)."""
    letters = list(text.lower())
    if not letters or any(a not in AXIS_LETTERS for a in letters):
        raise CliError(f"axes are letters of {AXIS_LETTERS!r}, like xyz; got {text!r}")
    if len(set(letters)) != len(letters):
        raise CliError(f"each axis once; got {text!r}")
    return letters


async def home(c: Client, args: argparse.Namespace, out: Output) -> int:
    """machine.home answers once the board says the cycle ended."""
    params: dict[str, Any] = {"machine": args.machine}
    if args.axes is not None:
        params["axes"] = axis_letters(args.axes)
    out.message(f"{args.machine}: homing ...")
    out.result(await c.call("machine.home", **params), f"{args.machine}: homed")
    return OK


async def zero(c: Client, args: argparse.Namespace, out: Output) -> int:
    """The named axes read 0 from now on in the active work coordinate system."""
    axes = {a: 0.0 for a in axis_letters(args.axes)}
    snap = await c.call("machine.zero", machine=args.machine, axes=axes)
    if out.json:
        out.print_json(snap)
    else:
        where = render.position(snap.get("work_position"), snap.get("units"))
        wcs = snap.get("wcs") or "the active WCS"
        out.out.print(
            f"{args.machine}: {''.join(axes).upper()} zeroed in {wcs}; work position {where}",
            markup=False,
            highlight=False,
        )
    return OK


async def probe(c: Client, args: argparse.Namespace, out: Output) -> int:
    """machine.probe: the operator touches the plate to the bit first, then it probes."""
    kind = "xyz" if args.xyz else "z"
    params: dict[str, Any] = {"machine": args.machine, "kind": kind, "wait": args.wait}
    for name in ("plate", "feed", "max_travel", "retract", "tool_diameter"):
        if getattr(args, name) is not None:
            params[name] = getattr(args, name)
    if args.confirmed:
        params["confirmed"] = True
    if kind == "xyz" and args.tool_diameter is None:
        raise CliError(
            "a corner probe (--xyz) needs --tool-diameter MM: the bit's side meets the walls"
        )
    out.message(
        f"{args.machine}: touch the plate to the bit to show the probe works, then lay it on"
        f" the work under the bit (waiting up to {args.wait:g} s); probing starts a second"
        " after the plate leaves the bit"
    )
    result = await c.call("machine.probe", **params)
    if out.json:
        out.print_json(result)
        return OK
    snap = await c.call("machine.status", machine=args.machine)
    touched = " ".join(f"{a.upper()}{v:.3f}" for a, v in result.get("position", {}).items())
    zeroed = "".join(result.get("zeroed", [])).upper()
    where = render.position(snap.get("work_position"), snap.get("units"))
    out.out.print(
        f"{args.machine}: probed {kind.upper()}, touched at {touched} (machine);"
        f" {zeroed} zeroed in {snap.get('wcs') or 'the active WCS'}; work position {where}",
        markup=False,
        highlight=False,
    )
    return OK


async def override(c: Client, args: argparse.Namespace, out: Output) -> int:
    params = {k: getattr(args, k) for k in ("feed", "spindle", "rapid")}
    given = {k: v for k, v in params.items() if v is not None}
    if not given:
        raise CliError("give --feed, --spindle or --rapid (percent)")
    now = await c.call("machine.override", machine=args.machine, **given)
    if out.json:
        out.print_json(now)
    else:
        shown = ", ".join(f"{k} {_percent(now.get(k))}" for k in ("feed", "spindle", "rapid"))
        out.out.print(f"{args.machine}: overrides {shown}", markup=False, highlight=False)
    return OK


def _percent(value: Any) -> str:
    return "unknown" if value is None else f"{value:g}%"


async def spindle(c: Client, args: argparse.Namespace, out: Output) -> int:
    if args.state == "off" and (args.ccw or args.speed is not None):
        raise CliError("off takes neither --speed nor --ccw")
    state = "off" if args.state == "off" else "ccw" if args.ccw else "cw"
    params: dict[str, Any] = {"machine": args.machine, "state": state}
    if args.speed is not None:
        params["speed"] = args.speed
    result = await c.call("machine.spindle", **params)
    speed = "" if args.speed is None else f" at {args.speed:g}"
    out.result(result, f"{args.machine}: spindle {state}{speed}")
    return OK


# -- frame, laser test, macros (issue 29) --------------------------------------------


async def _follow_job(c: Client, machine: str, job_id: int, out: Output) -> int:
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
    return _outcome(out, job, job_id)


async def frame(c: Client, args: argparse.Namespace, out: Output) -> int:
    """Upload FILE, then trace its bounding box (machine.frame) and follow that job."""
    path = Path(args.file)
    name = args.name or path.name
    await c.call("subscribe", topics=["job", "status", "exception"], machine=args.machine)
    await upload(c, path, name)
    params: dict[str, Any] = {"machine": args.machine, "file": name, "power": args.power}
    if args.feed is not None:
        params["feed"] = args.feed
    started = await c.call("machine.frame", **params)
    return await _follow_job(c, args.machine, int(started["job"]), out)


async def laser_test(c: Client, args: argparse.Namespace, out: Output) -> int:
    result = await c.call(
        "machine.laser_test", machine=args.machine, power=args.power, duration_s=args.seconds
    )
    out.result(result, f"{args.machine}: fired at {args.power:g}% for {args.seconds:g} s, beam off")
    return OK


async def macro(c: Client, args: argparse.Namespace, out: Output) -> int:
    """`macro list [MACHINE]` or `macro run MACHINE NAME [key=value ...]`."""
    if args.action == "list":
        params = {} if args.machine is None else {"machine": args.machine}
        found = await c.call("macro.list", **params)
        if out.json:
            out.print_json(found)
            return OK
        rows = [
            [m.get("machine", "-"), m["name"], _macro_params(m["params"]), _first_line(m["text"])]
            for m in found
        ]
        render.table(out.out, ["MACHINE", "MACRO", "PARAMS", "TEXT"], rows)
        return OK
    if args.machine is None or args.name is None:
        raise CliError("macro run needs MACHINE and NAME")
    values = {}
    for pair in args.params:
        key, eq, text = pair.partition("=")
        try:
            values[key] = float(text) if eq else None
        except ValueError:
            raise CliError(f"{pair!r}: a parameter is NAME=NUMBER") from None
        if values[key] is None:
            raise CliError(f"{pair!r}: a parameter is NAME=NUMBER")
    await c.call("subscribe", topics=["job", "status", "exception"], machine=args.machine)
    started = await c.call("macro.run", machine=args.machine, name=args.name, params=values)
    return await _follow_job(c, args.machine, int(started["job"]), out)


def _macro_params(params: dict[str, Any]) -> str:
    shown = []
    for name, p in params.items():
        default = "" if p.get("default") is None else f"={p['default']:g}"
        shown.append(f"{name}{default} ({p['min']:g}..{p['max']:g})")
    return ", ".join(shown) or "-"


def _first_line(text: str) -> str:
    lines = text.strip().splitlines()
    return lines[0] + (" ..." if len(lines) > 1 else "") if lines else ""


def _outcome(out: Output, job: dict[str, Any], job_id: int) -> int:
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
