"""The operator's day (issue 29): home, zero, probe, override, spindle, frame, laser
test and macros."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any, Final

from hostd.cli import render
from hostd.cli.client import Client
from hostd.cli.commands.base import (
    OK,
    CliError,
    follow_job,
)
from hostd.cli.commands.files import upload
from hostd.cli.render import Output

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
        where = render.position(snap.get("work_position"), render.work_units(snap))
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
    where = render.position(snap.get("work_position"), render.work_units(snap))
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
    return await follow_job(c, args.machine, int(started["job"]), out)


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
    return await follow_job(c, args.machine, int(started["job"]), out)


def _macro_params(params: dict[str, Any]) -> str:
    shown = []
    for name, p in params.items():
        default = "" if p.get("default") is None else f"={p['default']:g}"
        shown.append(f"{name}{default} ({p['min']:g}..{p['max']:g})")
    return ", ".join(shown) or "-"


def _first_line(text: str) -> str:
    lines = text.strip().splitlines()
    return lines[0] + (" ..." if len(lines) > 1 else "") if lines else ""
