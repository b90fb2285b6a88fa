"""Files: upload (in chunks), run (with its resume plan and tool-change prompt) and
analyze."""

from __future__ import annotations

import argparse
import base64
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO, Final

from hostd.cli import render
from hostd.cli.client import Client
from hostd.cli.commands.base import (
    FAILED,
    INTERRUPTED,
    OK,
    CliError,
    outcome,
)
from hostd.cli.interactive import CtrlC, StdinLines
from hostd.cli.progress import Detached, JobFollower
from hostd.cli.render import Output

UPLOAD_CHUNK: Final = 512 * 1024
# A chunk's JSON must stay under the daemon's 1 MiB line limit. Plain text
# grows a little when escaped (newlines become \n); a text full of control
# characters could grow sixfold, so past this size a chunk goes as base64.
MAX_TEXT_JSON: Final = 700 * 1024


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
    return outcome(out, job, job_id)


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
