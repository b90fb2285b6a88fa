"""A minimal G-code interpreter: the part of g2core's parser a host can observe.

It keeps the modal state (units, distance mode, feed, plane, motion mode,
G92 offsets, line number, the model position) and turns a line into planner
blocks, or into the status code g2core would answer with. Time, the planner
and the machine state are the board's business (board.py); this is pure.

Supported: N; G0 G1 G2 G3 (arcs with I/J/K offsets or R), G4 P (seconds),
G17-G19, G20/G21, G28.2 (homing), G28.3 (set position), G38.2-G38.5
(straight probes, cycle_probing.cpp), G40, G43 H and G49 (the tool length
offset from the tool table, `cm_set_tl_offset`), G53 (one
block in machine coordinates), G10 L2/L20 P0-P6 (the stored offsets,
`cm_set_g10_data`; L20 without G92, as canonical_machine.cpp) and G10 L1
P1-P32 (a tool table entry), G54-G59, G61
G61.1 G64, G80, G90/G91, G90.1/G91.1, G92/G92.1, G93/G94; M0 M1 (accepted,
no pause), M2/M30 (program end), M3 M4 M5 (the spindle, kept with each move),
M6 (the T selected becomes the reported `tool`), M7 M8 M9 (accepted); F S T
and the parameters P I J K R L. Any other
G code answers 131, any other M code 132.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from hostd.protocol.gcodewords import read_words
from hostd.protocol.status import Status
from hostd.sim.config import AXES

MM_PER_INCH = 25.4
TOOLS = 32  # g2core.h: entries in the tool table, from 1

_SUPPORTED_G = frozenset(
    {0, 1, 2, 3, 4, 10, 17, 18, 19, 20, 21, 28.2, 28.3, 38.2, 38.3, 38.4, 38.5, 40, 43, 49, 53}
    | {54, 55, 56, 57, 58, 59}
    | {61, 61.1, 64, 80, 90, 91, 90.1, 91.1, 92, 92.1, 93, 94}
)
_SUPPORTED_M = frozenset({0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 30})
_PARAMETERS = frozenset("FSTPIJKRLHDEQ")
# Plane -> (first axis, second axis, their arc offset letters).
_PLANES: dict[int, tuple[str, str, str, str]] = {
    17: ("x", "y", "I", "J"),
    18: ("z", "x", "K", "I"),
    19: ("y", "z", "J", "K"),
}

LimitCheck = Callable[[Mapping[str, float]], Status]


@dataclass(frozen=True, slots=True)
class Arc:
    """An arc in absolute machine coordinates: the plane, centre, radius and sweep."""

    axes: tuple[str, str]
    center: tuple[float, float]
    radius: float
    start_angle: float
    sweep: float  # radians, counter-clockwise positive


@dataclass(frozen=True, slots=True)
class Move:
    """A straight or arc move to `target` (machine mm) at `feed` mm/min."""

    target: dict[str, float]
    feed: float
    n: int
    rapid: bool = False
    arc: Arc | None = None
    # The spindle (or laser) as the move runs: both firmwares change it in step with the
    # moves (g2core queues M3/M4/M5 in the planner, spindle.cpp; grbl syncs first,
    # spindle_sync in spindle_control.c), so it is the interpreter's when the move is read.
    spindle: str = "M5"
    speed: float = 0.0


@dataclass(frozen=True, slots=True)
class Dwell:
    seconds: float
    n: int


@dataclass(frozen=True, slots=True)
class Home:
    """A homing cycle of `axes`: they travel to 0 and are homed afterwards."""

    axes: tuple[str, ...]
    n: int


@dataclass(frozen=True, slots=True)
class SetPosition:
    """G28.3: the machine now is at `values` on these axes, which count as homed."""

    values: dict[str, float]
    n: int


@dataclass(frozen=True, slots=True)
class Probe:
    """G38.2-G38.5: a straight feed toward `move.target` until the probe input trips.

    `on_contact`: it trips when the probe touches (G38.2/3), else when it stops
    touching (G38.4/5); `alarm`: a probe that never trips is an alarm (G38.2/4).
    """

    move: Move
    on_contact: bool
    alarm: bool

    @property
    def n(self) -> int:
        return self.move.n


@dataclass(frozen=True, slots=True)
class ProgramEnd:
    n: int


Block = Move | Dwell | Home | SetPosition | Probe | ProgramEnd
# G38.x: (trips on contact, alarms when it never trips) [cycle_probing.cpp cm_straight_probe]
_PROBES = {38.2: (True, True), 38.3: (True, False), 38.4: (False, True), 38.5: (False, False)}


@dataclass(frozen=True, slots=True)
class Outcome:
    """What a line did: its status, the blocks it queues, and its own N word (0 if none).

    `alarm` is the detail of the cm_alarm() the firmware raises with that status
    (a probe refused in cycle_probing.cpp), or empty when the status is only an answer.
    """

    status: Status
    blocks: tuple[Block, ...] = ()
    n: int = 0
    alarm: str = ""


def normalize(line: str) -> str:
    """As g2core does before parsing: comments and whitespace gone, upper-cased.

    `(...)` comments, and everything after `;` or a mid-line `%`, are dropped.
    """
    out: list[str] = []
    depth = 0
    for ch in line:
        if ch == "(":
            depth += 1
        elif ch == ")" and depth:
            depth -= 1
        elif depth:
            continue
        elif ch in ";%":
            break
        elif ch > " " and ch != "\x7f":
            out.append(ch.upper())
    return "".join(out)


def is_program_end(line: str) -> bool:
    """Exactly `M2` or `M30`: the G-code form of a clear (an N word defeats it)."""
    return normalize(line) in ("M2", "M30")


@dataclass
class Interpreter:
    """The G-code model: modal state and the position the next block starts from."""

    position: dict[str, float] = field(default_factory=lambda: dict.fromkeys(AXES, 0.0))
    offsets: dict[str, float] = field(default_factory=lambda: dict.fromkeys(AXES, 0.0))  # G92
    # G54..G59's stored offsets (mm): persistent settings (g54x.., config_app.cpp).
    coords: list[dict[str, float]] = field(
        default_factory=lambda: [dict.fromkeys(AXES, 0.0) for _ in range(6)]
    )
    spindle: str = "M5"
    speed: float = 0.0
    metric: bool = True
    absolute: bool = True
    feed: float | None = None  # mm/min, None until an F word is seen
    plane: int = 17
    motion: int | None = 0
    coord: int = 1  # 1..6 for G54..G59
    path: int = 2  # 0 G61, 1 G61.1, 2 G64
    inverse_time: bool = False
    line: int = 0  # model line number (last N)
    # The tool table (G10 L1, tt.tt_offset) and the length offset in force (G43, G49:
    # cm->tool_offset, part of the combined offset).
    tools: dict[int, dict[str, float]] = field(default_factory=dict)
    tool_offset: dict[str, float] = field(default_factory=lambda: dict.fromkeys(AXES, 0.0))
    # T writes the tool to select, M6 makes it the active tool, reported as `tool`
    # (canonical_machine.cpp:1392-1408 `cm_select_tool`, `_exec_change_tool`).
    tool_select: int = 0
    tool: int = 0

    def copy(self) -> Interpreter:
        return Interpreter(
            position=dict(self.position),
            offsets=dict(self.offsets),
            coords=[dict(c) for c in self.coords],
            spindle=self.spindle,
            speed=self.speed,
            metric=self.metric,
            absolute=self.absolute,
            feed=self.feed,
            plane=self.plane,
            motion=self.motion,
            coord=self.coord,
            path=self.path,
            inverse_time=self.inverse_time,
            line=self.line,
            tools={n: dict(t) for n, t in self.tools.items()},
            tool_offset=dict(self.tool_offset),
            tool_select=self.tool_select,
            tool=self.tool,
        )

    @property
    def scale(self) -> float:
        """mm per program unit."""
        return 1.0 if self.metric else MM_PER_INCH

    def work_offset(self) -> dict[str, float]:
        """The offset in force (mm): the coordinate system's plus G92 (cm_get_combined_offset)."""
        coord = self.coords[self.coord - 1]
        return {a: coord[a] + self.offsets[a] + self.tool_offset[a] for a in AXES}

    def sync(self, position: Mapping[str, float]) -> None:
        """The planner was flushed: the next block starts where the machine stands."""
        self.position = {a: float(position[a]) for a in AXES}

    def program_end(self) -> None:
        """M2/M30 (and job kill): g2core restores the G-code defaults."""
        self.offsets = dict.fromkeys(AXES, 0.0)
        self.spindle = "M5"  # _exec_program_finalize: spindle off
        self.absolute = True
        self.plane = 17
        self.motion = 1
        self.coord = 1
        self.path = 2
        self.inverse_time = False

    def execute(self, line: str, limits: LimitCheck) -> Outcome:
        """Interpret one line; modal state and position change only if it succeeds."""
        text = normalize(line)
        if not text:
            return Outcome(Status.OK)
        words = _words(text)
        if isinstance(words, Status):
            return Outcome(words)
        n = 0
        if words and words[0][0] == "N":
            n = int(words[0][1])
            words = words[1:]
        work = self.copy()
        try:
            blocks = work._run(words, n, limits)
        except _Refused as refused:
            return Outcome(refused.status, n=n, alarm=refused.alarm)
        if n:
            work.line = n
        for name in work.__dataclass_fields__:
            setattr(self, name, getattr(work, name))
        return Outcome(Status.OK, tuple(blocks), n)

    # --- one block, on a working copy

    def _run(self, words: list[tuple[str, float]], n: int, limits: LimitCheck) -> list[Block]:
        gcodes: list[float] = []
        mcodes: list[float] = []
        params: dict[str, float] = {}
        axes: dict[str, float] = {}
        for letter, value in words:
            if letter == "G":
                gcodes.append(round(value, 1))
            elif letter == "M":
                mcodes.append(round(value, 1))
            elif letter.lower() in AXES:
                axes[letter.lower()] = value
            elif letter in _PARAMETERS:
                params[letter] = value
            elif letter in "ABCUVW":
                raise _Refused(Status.AXIS_IS_NOT_CONFIGURED)
            else:
                raise _Refused(Status.GCODE_GENERIC_INPUT_ERROR)
        for g in gcodes:
            if g not in _SUPPORTED_G:
                raise _Refused(Status.GCODE_COMMAND_UNSUPPORTED)
        for m in mcodes:
            if m not in _SUPPORTED_M:
                raise _Refused(Status.MCODE_COMMAND_UNSUPPORTED)

        line = n or self.line
        blocks: list[Block] = []
        gset = set(gcodes)
        # g2core's order of execution within a block (gcode_parser.cpp).
        if 20 in gset:
            self.metric = False
        if 21 in gset:
            self.metric = True
        if 93 in gset:
            self.inverse_time = True
        if 94 in gset:
            self.inverse_time = False
        if "F" in params:
            if params["F"] <= 0:
                raise _Refused(Status.GCODE_GENERIC_INPUT_ERROR)
            self.feed = params["F"] * self.scale
        if "S" in params:
            self.speed = params["S"]
        if "T" in params:  # gcode_parser.cpp:962-963: T, then M6, in one block
            tool = math.trunc(params["T"])  # :855 `(uint8_t)trunc(value)`
            if not 0 <= tool <= TOOLS:
                raise _Refused(Status.T_WORD_IS_INVALID)  # cm_select_tool
            self.tool_select = tool
        if 6 in mcodes:
            self.tool = self.tool_select
        for m in mcodes:
            if m in (3, 4, 5):
                self.spindle = f"M{int(m)}"
        for plane in (17, 18, 19):
            if plane in gset:
                self.plane = plane
        if 90 in gset:
            self.absolute = True
        if 91 in gset:
            self.absolute = False
        for g in (54, 55, 56, 57, 58, 59):
            if g in gset:
                self.coord = int(g) - 53
        for g, mode in ((61, 0), (61.1, 1), (64, 2)):
            if g in gset:
                self.path = mode
        if 4 in gset:
            if "P" not in params:
                raise _Refused(Status.P_WORD_IS_MISSING)
            if params["P"] < 0:
                raise _Refused(Status.P_WORD_IS_NEGATIVE)
            blocks.append(Dwell(params["P"], line))

        axes_used = False
        if 28.2 in gset:
            homed = tuple(a for a in AXES if a in axes) or AXES
            for a in homed:
                self.position[a] = 0.0
            blocks.append(Home(homed, line))
            axes_used = True
        elif 28.3 in gset:
            values = {a: v * self.scale for a, v in axes.items()}
            self.position.update(values)
            blocks.append(SetPosition(values, line))
            axes_used = True
        elif 10 in gset:
            self._g10(axes, params)
            axes_used = True
        elif 92 in gset:
            coord = self.coords[self.coord - 1]
            for a, v in axes.items():
                self.offsets[a] = self.position[a] - coord[a] - v * self.scale
            axes_used = True
        elif 92.1 in gset:
            self.offsets = dict.fromkeys(AXES, 0.0)
        if 43 in gset:
            # cm_set_tl_offset: the H word's entry (H0 or none: the current tool, which
            # this model does not track: entry 0, no offset).
            h = int(params.get("H", 0))
            if not 0 <= h <= TOOLS:
                raise _Refused(Status.H_WORD_IS_INVALID)
            entry = self.tools.get(h, {})
            self.tool_offset = {a: entry.get(a, 0.0) for a in AXES}
        elif 49 in gset:
            self.tool_offset = dict.fromkeys(AXES, 0.0)  # cm_cancel_tl_offset

        probe = next((g for g in gcodes if g in _PROBES), None)
        if probe is not None:
            blocks.append(self._probe(axes, line, *_PROBES[probe]))
            axes_used = True
        for g in (0, 1, 2, 3):
            if g in gset:
                self.motion = int(g)
        if 80 in gset:
            self.motion = None
        if axes and not axes_used:
            blocks.append(self._motion(axes, params, line, machine=53 in gset, limits=limits))

        ends = any(m in (2, 30) for m in mcodes)
        if ends:
            self.program_end()
            blocks.append(ProgramEnd(line))
        return blocks

    def _g10(self, axes: dict[str, float], params: dict[str, float]) -> None:
        """G10 L2 (the offset) or L20 (the current position reads as given, G92 not
        counted: canonical_machine.cpp cm_set_g10_data); P0 is the active system."""
        if params.get("L") == 1.0 and "P" in params:
            tool = int(params["P"])
            if not 1 <= tool <= TOOLS:
                raise _Refused(Status.P_WORD_IS_INVALID)
            entry = self.tools.setdefault(tool, dict.fromkeys(AXES, 0.0))
            for a, v in axes.items():
                entry[a] = v * self.scale
            return
        if params.get("L") not in (2.0, 20.0) or "P" not in params:
            raise _Refused(Status.GCODE_COMMAND_UNSUPPORTED)
        p = int(params["P"])
        if not 0 <= p <= 6:
            raise _Refused(Status.P_WORD_IS_INVALID)
        coord = self.coords[(p or self.coord) - 1]
        for a, v in axes.items():
            value = v * self.scale
            coord[a] = (
                value
                if params["L"] == 2.0
                else self.position[a] - value - self.tool_offset[a]  # L20, as g2core
            )

    def _motion(
        self,
        axes: dict[str, float],
        params: dict[str, float],
        line: int,
        *,
        machine: bool,
        limits: LimitCheck,
    ) -> Move:
        if self.motion is None:
            raise _Refused(Status.GCODE_GENERIC_INPUT_ERROR)
        if machine and self.motion not in (0, 1):
            raise _Refused(Status.GCODE_G53_WITHOUT_G0_OR_G1)
        target = dict(self.position)
        offset = self.work_offset()
        for a, v in axes.items():
            if machine:
                target[a] = v * self.scale
            elif self.absolute:
                target[a] = v * self.scale + offset[a]
            else:
                target[a] = self.position[a] + v * self.scale
        rapid = self.motion == 0
        if not rapid and self.feed is None:
            raise _Refused(Status.FEEDRATE_NOT_SPECIFIED)
        arc = None if self.motion in (0, 1) else self._arc(target, params)
        status = limits(target)
        if status != Status.OK:
            raise _Refused(status)
        self.position = target
        feed = self.feed or 0.0
        return Move(target, feed, line, rapid, arc, self.spindle, self.speed)

    def _probe(self, axes: dict[str, float], line: int, on_contact: bool, alarm: bool) -> Probe:
        """cm_straight_probe: refusals raise an alarm; no soft limits while probing."""
        if not self.feed:
            raise _Refused(Status.FEEDRATE_NOT_SPECIFIED, alarm="Feedrate is zero")
        if not axes:
            raise _Refused(Status.AXIS_IS_MISSING, alarm="Axis is missing")
        target = dict(self.position)
        offset = self.work_offset()
        for a, v in axes.items():
            if self.absolute:
                target[a] = v * self.scale + offset[a]
            else:
                target[a] = self.position[a] + v * self.scale
        # _probe_restore_settings: the motion mode is cancelled when the cycle ends;
        # where the tool ends up is known only then (the board syncs this model).
        self.motion = None
        self.position = target
        return Probe(Move(target, self.feed, line), on_contact, alarm)

    def _arc(self, target: dict[str, float], params: dict[str, float]) -> Arc:
        first, second, off1, off2 = _PLANES[self.plane]
        x0, y0 = self.position[first], self.position[second]
        x1, y1 = target[first], target[second]
        clockwise = self.motion == 2
        if "R" in params:
            radius = params["R"] * self.scale
            dx, dy = x1 - x0, y1 - y0
            chord = math.hypot(dx, dy)
            if chord == 0:
                raise _Refused(Status.ARC_ENDPOINT_IS_STARTING_POINT)
            h2 = 4 * radius * radius - chord * chord
            if h2 < -1e-6:
                raise _Refused(Status.ARC_RADIUS_OUT_OF_TOLERANCE)
            h = -math.sqrt(max(h2, 0.0)) / chord
            if not clockwise:
                h = -h
            if radius < 0:
                h, radius = -h, -radius
            cx, cy = x0 + 0.5 * (dx - dy * h), y0 + 0.5 * (dy + dx * h)
        elif off1 in params or off2 in params:
            cx = x0 + params.get(off1, 0.0) * self.scale
            cy = y0 + params.get(off2, 0.0) * self.scale
            radius = math.hypot(x0 - cx, y0 - cy)
        else:
            raise _Refused(Status.ARC_OFFSETS_MISSING_FOR_SELECTED_PLANE)
        if radius == 0:
            raise _Refused(Status.ARC_SPECIFICATION_ERROR)
        a0 = math.atan2(y0 - cy, x0 - cx)
        a1 = math.atan2(y1 - cy, x1 - cx)
        sweep = a1 - a0
        full = math.hypot(x1 - x0, y1 - y0) < 1e-9
        if clockwise:
            if sweep >= 0 or full:
                sweep -= 2 * math.pi
        elif sweep <= 0 or full:
            sweep += 2 * math.pi
        return Arc((first, second), (cx, cy), radius, a0, sweep)


class _Refused(Exception):
    def __init__(self, status: Status, *, alarm: str = "") -> None:
        super().__init__(status.name)
        self.status = status
        self.alarm = alarm


def _words(text: str) -> list[tuple[str, float]] | Status:
    """The words of a normalized line (the shared tokenizer), or the status it answers."""
    words, end = read_words(text)
    if end < len(text):
        if text[end].isalpha():
            return Status.BAD_NUMBER_FORMAT
        return Status.GCODE_GENERIC_INPUT_ERROR
    return [(letter, float(number)) for letter, number in words]
