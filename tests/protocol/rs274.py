"""LinuxCNC's standalone interpreter `rs274` as a reference for the modal model.

`run(path, probe_lines)` runs `rs274 -g` on a copy of the file with, after each
probed line, `(debug,...)` comments that print the interpreter's own modal state
through its predefined named parameters (#<_metric>, #<_plane>, #<_x> ...).
The canonical commands it prints (STRAIGHT_FEED, ARC_FEED, SET_G5X_OFFSET,
USE_LENGTH_UNITS ...) are replayed here, independently of hostd's code, for
the offsets at each probe and the bounds of every move in machine coordinates.

rs274 comes from Debian's `linuxcnc-uspace` (`.ci/run` installs it). Without it
the tests fail, with the command that installs it: they never skip.
"""

from __future__ import annotations

import math
import re
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

MM_PER_INCH = 25.4
INSTALL = "apt-get install -y --no-install-recommends linuxcnc-uspace (what .ci/run does)"

# rs274 refuses a line over 256 characters: the probe is split over several comments.
PROBES = (
    "m=#<_metric> abs=#<_absolute> pl=#<_plane> cs=#<_coord_system> mm=#<_motion_mode>",
    "f=#<_feed> rpm=#<_rpm> son=#<_spindle_on> cw=#<_spindle_cw> fl=#<_flood> mi=#<_mist>",
    "t=#<_current_tool> sel=#<_selected_tool> ijk=#<_ijk_absolute_mode>",
    "inv=#<_inverse_time> upm=#<_units_per_minute> upr=#<_units_per_rev>",
    "x=#<_x> y=#<_y> z=#<_z> a=#<_a> b=#<_b> c=#<_c>",
)
_CANON = re.compile(r"^\s*\d+ N\S*\s+([A-Z_0-9]+)\((.*)\)\s*$")
_PROBE = re.compile(r"^PROBE (\d+) (.*)$")
_AXES = ("x", "y", "z", "a", "b", "c")


def binary() -> str:
    found = shutil.which("rs274")
    if found is None:
        raise AssertionError(f"rs274 (LinuxCNC) is not installed: {INSTALL}")
    return found


@dataclass
class Probe:
    """The interpreter's state after one line of the file."""

    line: int
    values: dict[str, float]  # the named parameters, by the short names of PROBES
    units: str  # G20 / G21, from USE_LENGTH_UNITS
    g5x: dict[str, float]  # mm, the active coordinate system's offset
    g5x_index: int
    g92: dict[str, float]  # mm
    feed_rate: float | None  # SET_FEED_RATE, current units


@dataclass
class Run:
    probes: dict[int, Probe] = field(default_factory=dict)
    bounds: dict[str, list[float]] = field(default_factory=dict)  # mm, machine coordinates
    moves: int = 0
    arcs: int = 0
    errors: list[str] = field(default_factory=list)
    canon: list[tuple[str, str]] = field(default_factory=list)


def instrument(lines: list[str], probe_lines: set[int]) -> list[str]:
    out = []
    for number, text in enumerate(lines, start=1):
        out.append(text)
        if number in probe_lines:
            out.extend(f"(debug,PROBE {number} {probe})" for probe in PROBES)
    return out


def run(path: Path, probe_lines: set[int], work: Path, *, block_delete: bool = False) -> Run:
    lines = path.read_text().splitlines()
    copy = work / path.name
    copy.write_text("\n".join(instrument(lines, probe_lines)) + "\n")
    # Tools 1..20, all of length 0: T and M6 are accepted, G43 offsets nothing.
    table = work / "tools.tbl"
    table.write_text("".join(f"T{t} P{t} Z0 D0.1\n" for t in range(1, 21)))
    args = [binary(), "-g", "-t", str(table)] + (["-b"] if block_delete else []) + [str(copy)]
    done = subprocess.run(args, capture_output=True, text=True, timeout=30, cwd=work, check=False)
    return replay(done.stdout, done.stderr)


def replay(stdout: str, stderr: str) -> Run:
    result = Run()
    scale = 1.0
    units = "G21"
    g5x = dict.fromkeys(_AXES, 0.0)
    g5x_index = 1
    g92 = dict.fromkeys(_AXES, 0.0)
    feed: float | None = None
    position = dict.fromkeys(_AXES, 0.0)  # program frame, current units
    plane = "XY"
    for text in stdout.splitlines():
        m = _CANON.match(text)
        if m is None:
            continue
        name, args = m.group(1), m.group(2)
        result.canon.append((name, args))
        if name == "MESSAGE":
            probe = _PROBE.match(args.strip('"'))
            if probe is not None:
                number = int(probe.group(1))
                found = result.probes.get(number)
                if found is None:
                    found = Probe(number, {}, units, dict(g5x), g5x_index, dict(g92), feed)
                    result.probes[number] = found
                for pair in probe.group(2).split():
                    key, _, value = pair.partition("=")
                    found.values[key] = float(value)
            continue
        values = [v.strip() for v in re.split(r"[ ,]+", args) if v.strip()]
        if name == "USE_LENGTH_UNITS":
            units = "G20" if "INCHES" in args else "G21"
            scale = MM_PER_INCH if units == "G20" else 1.0
        elif name == "SET_G5X_OFFSET":
            g5x_index = int(values[0])
            g5x = _axes(values[1:7], scale)
        elif name == "SET_G92_OFFSET":
            g92 = _axes(values[0:6], scale)
        elif name == "SET_FEED_RATE":
            feed = float(values[0])
        elif name == "SELECT_PLANE":
            plane = args.rsplit("_", 1)[-1]
        elif name in ("STRAIGHT_TRAVERSE", "STRAIGHT_FEED", "STRAIGHT_PROBE"):
            start = dict(position)
            position = dict(zip(_AXES, map(float, values[0:6]), strict=True))
            result.moves += 1
            if position != start:  # `G0` alone is a move to where it stands: no extent
                _extend(result, position, scale, g5x, g92)
        elif name == "ARC_FEED":
            result.moves += 1
            result.arcs += 1
            position = _arc(result, position, plane, values, scale, g5x, g92)
    result.errors = [line for line in stderr.splitlines() if line.strip()]
    return result


def _axes(values: list[str], scale: float) -> dict[str, float]:
    return {
        a: float(v) * (scale if i < 3 else 1.0)
        for i, (a, v) in enumerate(zip(_AXES, values, strict=False))
    }


def _machine(pos: dict[str, float], scale: float, g5x: dict[str, float], g92: dict[str, float]):
    return {a: pos[a] * (scale if i < 3 else 1.0) + g5x[a] + g92[a] for i, a in enumerate(_AXES)}


def _extend(result: Run, end, scale, g5x, g92) -> None:  # type: ignore[no-untyped-def]
    for a, v in _machine(end, scale, g5x, g92).items():
        lo_hi = result.bounds.setdefault(a, [v, v])
        lo_hi[0] = min(lo_hi[0], v)
        lo_hi[1] = max(lo_hi[1], v)


_PLANE_AXES = {"XY": ("x", "y", "z"), "XZ": ("z", "x", "y"), "YZ": ("y", "z", "x")}


def _arc(result: Run, position, plane, values, scale, g5x, g92):  # type: ignore[no-untyped-def]
    """ARC_FEED(first_end, second_end, first_centre, second_centre, rotation, axis_end, a, b, c),
    sampled finely enough (every 0.1 degree) for the bounds to within 1e-3 of the radius."""
    first, second, helix = _PLANE_AXES[plane]
    e1, e2, c1, c2 = (float(v) for v in values[0:4])
    rotation = int(values[4])
    axis_end = float(values[5])
    s1, s2 = position[first], position[second]
    a0 = math.atan2(s2 - c2, s1 - c1)
    a1 = math.atan2(e2 - c2, e1 - c1)
    radius = math.hypot(s1 - c1, s2 - c2)
    ccw = rotation > 0
    sweep = (a1 - a0) if ccw else (a0 - a1)
    sweep %= 2 * math.pi
    if sweep < 1e-9:
        sweep = 2 * math.pi
    sweep += 2 * math.pi * (abs(rotation) - 1)
    steps = max(2, int(math.degrees(sweep) * 10))
    start = dict(position)
    end = dict(position)
    end[first], end[second], end[helix] = e1, e2, axis_end
    for i, a in enumerate(("a", "b", "c")):
        end[a] = float(values[6 + i])
    for k in range(steps + 1):
        angle = a0 + (sweep if ccw else -sweep) * k / steps
        point = dict(start)
        point[first] = c1 + radius * math.cos(angle)
        point[second] = c2 + radius * math.sin(angle)
        point[helix] = start[helix] + (axis_end - start[helix]) * k / steps
        _extend(result, point, scale, g5x, g92)
    _extend(result, end, scale, g5x, g92)
    return end
