"""A snapshot of the modal state, and the G-code that puts a fresh controller into it.

Modes are kept as the G or M code that selects them (`units == "G20"`), which is
what a preamble writes and what a reader of a G-code file recognises. Lengths
are in millimetres unless a name says otherwise; a position or offset that the
file cannot tell (set by the machine before the job, or after G28 with an
unknown home) is None.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

AXES = ("x", "y", "z", "a", "b", "c")
LINEAR = ("x", "y", "z")
MM_PER_INCH = 25.4
WCS = ("G54", "G55", "G56", "G57", "G58", "G59", "G59.1", "G59.2", "G59.3")

Units = Literal["G20", "G21"]
Distance = Literal["G90", "G91"]
ArcDistance = Literal["G90.1", "G91.1"]
Plane = Literal["G17", "G18", "G19"]
FeedMode = Literal["G93", "G94", "G95"]
Spindle = Literal["M3", "M4", "M5"]
Path = Literal["G61", "G61.1", "G64"]

Position = dict[str, float | None]


@dataclass(frozen=True, slots=True)
class ModalState:
    """The controller's modal state after a line, as the file sets it."""

    line: int  # file line number (1-based) of the last line read; 0 before any
    n: int | None  # the last N word
    units: Units
    distance: Distance
    arc_distance: ArcDistance
    plane: Plane
    wcs: str  # "G54" .. "G59.3"
    feed_mode: FeedMode
    feed: float | None  # F in the current units (per minute, or per rev in G95); None if unset
    motion: str  # G0 G1 G2 G3 G38.2 .. G80 G81 ..
    path: Path
    spindle: Spindle
    speed: float | None  # S: spindle speed or laser power; None if never set
    mist: bool  # M7
    flood: bool  # M8
    tool: int | None  # the tool in the spindle (after M6); None if unknown
    selected_tool: int | None  # the last T word
    tool_length: str  # G43 / G43.1 / G49 (the offset value itself is the machine's)
    machine: Position  # mm, machine coordinates of the programmed point (G53 frame)
    work: Position  # current units, in the active coordinate system, after G92
    wcs_offsets: Mapping[str, Position]  # mm, per coordinate system; None where unknown
    wcs_set: Mapping[str, tuple[str, ...]]  # the axes this file set with G10, per system
    g92: Position  # mm, the G92 offset in force (zero when off or suspended)
    g92_stored: Position  # mm, the offset G92.3 would restore
    ended: bool  # M2/M30 was read
    # The tool length offset in force (mm): 0 under G49, G43.1's Z; None under G43 (the
    # value is in the machine's tool table), with `tool_h` its H word.
    tlo: float | None = 0.0
    tool_h: int | None = None
    plunge_feed: float | None = None  # mm/min: the last feed move along Z alone (G94)
    # What the file's G10 wrote, per system (mm), where the model kept the board's offsets
    # instead (a resume); and the last line with a G10 that set one, with a G53 move.
    wcs_file: Mapping[str, Position] | None = None
    g10_line: int | None = None
    g53_line: int | None = None

    @property
    def scale(self) -> float:
        """mm per program unit."""
        return MM_PER_INCH if self.units == "G20" else 1.0

    def preamble(self, tool_change: bool = True) -> list[str]:
        """G-code that puts a freshly reset controller into this modal state.

        In the order a controller needs it: units first (every later number is read in
        them), then the modes, the coordinate system, the tool and its length offset,
        feed, spindle or laser, coolant. It never writes a coordinate system's offset
        (G10): the board stores those, and keeps what the file's G10 wrote when the job
        ran it; a resume says so instead (resume.py). What it cannot restore on its own
        (a G92 offset depends on where the machine stands) is listed by `unrestorable`;
        `g92_line` writes it for a known position.
        """
        lines = [
            self.units,
            f"{self.plane} {self.distance} {self.arc_distance} {self.feed_mode} {self.path}",
        ]
        lines.append(self.wcs)
        if self.tool is not None:
            lines.append(f"T{self.tool} M6" if tool_change else f"T{self.tool}")
        if self.selected_tool is not None and self.selected_tool != self.tool:
            lines.append(f"T{self.selected_tool}")
        if self.tool_length == "G43.1" and self.tlo is not None:
            lines.append(f"G43.1 Z{_num(self.tlo / self.scale, 4)}")
        elif self.tool_length == "G43":
            lines.append("G43" if self.tool_h is None else f"G43 H{self.tool_h}")
        if self.feed is not None and self.feed_mode != "G93":
            lines.append(f"F{_num(self.feed, 3)}")
        if self.spindle != "M5" and self.speed is not None:
            lines.append(f"S{_num(self.speed, 3)} {self.spindle}")
        elif self.speed is not None:
            lines.append(f"S{_num(self.speed, 3)}")
        if self.mist:
            lines.append("M7")
        if self.flood:
            lines.append("M8")
        return lines

    def unrestorable(self) -> list[str]:
        """What `preamble` does not restore: say it to whoever resumes."""
        out = []
        if any(v != 0 for v in self.g92.values()):
            out.append(
                "a G92 offset is in force: it depends on the machine's position when it is "
                "set again (g92_line)"
            )
        if self.tool_length == "G43":
            out.append("G43: the tool length offset value is the machine's (its tool table)")
        if self.feed_mode == "G93":
            out.append("G93: inverse-time feed is given on every move, not restored")
        return out

    def g92_line(self, machine: Mapping[str, float]) -> str | None:
        """`G92 ...` that recreates the G92 offset with the machine standing at `machine` (mm)."""
        offsets = self.wcs_offsets.get(self.wcs, {})
        words = []
        for axis in AXES:
            g92 = self.g92.get(axis)
            if not g92:
                continue
            wcs = offsets.get(axis)
            if g92 is None or wcs is None or axis not in machine:
                return None
            work = machine[axis] - wcs - g92
            words.append(f"{axis.upper()}{_num(_from_mm(work, axis, self.scale), 4)}")
        return f"G92 {' '.join(words)}" if words else None


def _from_mm(value: float, axis: str, scale: float) -> float:
    return value / scale if axis in LINEAR else value


def _num(value: float, decimals: int) -> str:
    """Plain digits, trailing zeros dropped, never `-0` or an exponent."""
    text = f"{value:.{decimals}f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text
