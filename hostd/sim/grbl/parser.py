"""grbl's G-code parser, the part a host can observe (gnea/grbl gcode.c, grblHAL gcode.c).

A line is checked as a whole before anything changes (gc_execute_block's
"error-check then execute" design): on an error the modal state and the
position stay as they were and the line's `error:N` is the whole effect.

Supported: N; G0 G1 G2 G3 (I/J/K or R), G4 P, G10 L2/L20 P0-6, G17-G19,
G20/G21, G38.2-G38.5, G43.1 Z/G49 (the dynamic tool length offset), G53, G54-G59,
G80, G90/G91, G91.1, G92/G92.1,
G93/G94; M0 M1 M2 M30, M3 M4 M5, M7 M8 M9; F S T. Anything else is error:20.
Jogging (`$J=`, jog.c / gc_execute_block's jog branch) takes only G20 G21
G90 G91 G53, axis words, F and N, and needs F.

Pure: blocks out, using the g2core simulator's block types and motion
timing (hostd/sim/gcode.py, motion.py).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace

from hostd.protocol.gcodewords import read_words
from hostd.sim.config import AXES
from hostd.sim.gcode import Arc, Move
from hostd.sim.grbl.codes import Error

MM_PER_INCH = 25.4
_PLANES: dict[int, tuple[str, str, str, str]] = {
    17: ("x", "y", "I", "J"),
    18: ("z", "x", "K", "I"),
    19: ("y", "z", "J", "K"),
}
# Modal groups (gcode.h MODAL_GROUP_G*), for error:21.
_G_GROUP: dict[float, str] = {
    **dict.fromkeys((4.0, 10.0, 28.0, 30.0, 53.0, 92.0, 92.1), "nonmodal"),
    **dict.fromkeys((0.0, 1.0, 2.0, 3.0, 38.2, 38.3, 38.4, 38.5, 80.0), "motion"),
    **dict.fromkeys((17.0, 18.0, 19.0), "plane"),
    **dict.fromkeys((90.0, 91.0), "distance"),
    91.1: "arc_distance",
    **dict.fromkeys((43.1, 49.0), "tool_length"),
    **dict.fromkeys((93.0, 94.0), "feed_mode"),
    **dict.fromkeys((20.0, 21.0), "units"),
    **dict.fromkeys((54.0, 55.0, 56.0, 57.0, 58.0, 59.0), "coord"),
}
_M_GROUP: dict[float, str] = {
    **dict.fromkeys((0.0, 1.0, 2.0, 30.0), "stopping"),
    **dict.fromkeys((3.0, 4.0, 5.0), "spindle"),
    **dict.fromkeys((7.0, 8.0, 9.0), "coolant"),
}
_VALUE_WORDS = frozenset("FIJKLNPRSTXYZ")
_JOG_G = frozenset({20.0, 21.0, 90.0, 91.0, 53.0})
_PROBES = {38.2: (True, True), 38.3: (True, False), 38.4: (False, True), 38.5: (False, False)}

TravelCheck = Callable[[Mapping[str, float]], bool]


@dataclass(frozen=True, slots=True)
class Probe:
    """A G38.x move: toward `move.target` until the probe reads `toward` (contact)."""

    move: Move
    toward: bool  # G38.2/.3 seek contact; G38.4/.5 seek loss of contact
    fail_alarm: bool  # G38.2/.4 alarm on no contact; .3/.5 do not


@dataclass(frozen=True, slots=True)
class Executed:
    """What an accepted line asks of the machine, in the order grbl does it."""

    moves: tuple[Move, ...] = ()
    dwell: float | None = None  # G4: seconds, after the planner empties
    probe: Probe | None = None
    stop: str | None = None  # "M0", "M1", "M2" or "M30", after the planner empties
    offsets_changed: bool = False  # a WCO change (grblHAL: WCO in the next report)
    stores: bool = False  # G10 L2/L20 writes the offsets to EEPROM / flash


@dataclass
class Modal:
    """gc_state: the modal groups and the parser's idea of the position (machine mm)."""

    position: dict[str, float] = field(default_factory=lambda: dict.fromkeys(AXES, 0.0))
    wcs: list[dict[str, float]] = field(
        default_factory=lambda: [dict.fromkeys(AXES, 0.0) for _ in range(6)]
    )
    g92: dict[str, float] = field(default_factory=lambda: dict.fromkeys(AXES, 0.0))
    coord: int = 0  # 0..5 for G54..G59
    motion: float = 0.0
    plane: int = 17
    metric: bool = True
    absolute: bool = True
    inverse_time: bool = False
    feed: float = 0.0  # mm/min, 0 = undefined
    spindle: str = "M5"
    speed: float = 0.0
    coolant: frozenset[str] = frozenset()
    tool: int = 0
    line: int = 0
    program_flow: str = ""
    probe: dict[str, float] = field(default_factory=lambda: dict.fromkeys(AXES, 0.0))
    probe_ok: bool = False
    tlo: float = 0.0  # G43.1's tool length offset along Z, mm (gc_state.tool_length_offset)

    def copy(self) -> Modal:
        return replace(
            self,
            position=dict(self.position),
            wcs=[dict(w) for w in self.wcs],
            g92=dict(self.g92),
            probe=dict(self.probe),
        )

    def wco(self) -> dict[str, float]:
        """The work coordinate offset: the G54-G59 offset plus G92, and on Z the tool
        length offset (gnea/grbl report.c, the WCO; gcode.c adds it to every target)."""
        return {
            a: self.wcs[self.coord][a] + self.g92[a] + (self.tlo if a == "z" else 0.0) for a in AXES
        }

    def reset(self) -> None:
        """gc_init() after a soft reset: modes back to defaults; G54-G59 persist (EEPROM),
        G92 and the probe result do not (gnea/grbl doc/markdown/commands.md `$#`)."""
        fresh = Modal(position=dict(self.position), wcs=self.wcs)
        for name in self.__dataclass_fields__:
            setattr(self, name, getattr(fresh, name))

    def program_end(self) -> None:
        """M2/M30 (gc_execute_block, "program flow"): LinuxCNC's reset of some modes."""
        self.coord = 0
        self.g92 = dict.fromkeys(AXES, 0.0)
        self.motion = 1.0
        self.plane = 17
        self.absolute = True
        self.inverse_time = False
        self.spindle = "M5"
        self.coolant = frozenset()


def normalize(line: str) -> str:
    """protocol.c: comments dropped, spaces removed, upper-cased."""
    out: list[str] = []
    paren = semi = False
    for ch in line:
        if semi:
            break
        if paren:
            paren = ch != ")"
        elif ch == "(":
            paren = True
        elif ch == ";":
            semi = True
        elif ch > " ":
            out.append(ch.upper())
    return "".join(out)


def _words(text: str) -> list[tuple[str, float]] | Error:
    """The words of a normalized line (the shared tokenizer), or the error it answers."""
    words, end = read_words(text)
    if end < len(text):
        if not text[end].isalpha():
            return Error.EXPECTED_COMMAND_LETTER
        return Error.BAD_NUMBER_FORMAT
    return [(letter, float(number)) for letter, number in words]


class _Refused(Exception):
    def __init__(self, error: Error) -> None:
        super().__init__(error.name)
        self.error = error


def execute(
    modal: Modal, line: str, *, travel_ok: TravelCheck, jog: bool = False
) -> Error | Executed:
    """Check and run one block against `modal` (changed only on success)."""
    text = normalize(line)
    words = _words(text)
    if isinstance(words, Error):
        return words
    work = modal.copy()
    try:
        done = _block(work, words, travel_ok, jog)
    except _Refused as refused:
        return refused.error
    if not jog:  # a jog leaves the parser's modes alone (gc_execute_block, jog branch)
        for name in modal.__dataclass_fields__:
            setattr(modal, name, getattr(work, name))
    else:
        modal.position = work.position
    return done


def _block(m: Modal, words: list[tuple[str, float]], travel_ok: TravelCheck, jog: bool) -> Executed:
    gcodes: list[float] = []
    mcodes: list[float] = []
    values: dict[str, float] = {}
    groups: set[str] = set()
    for letter, value in words:
        if letter in "GM":
            code = round(value, 1)
            table = _G_GROUP if letter == "G" else _M_GROUP
            group = table.get(code)
            if group is None:
                raise _Refused(Error.UNSUPPORTED_COMMAND)
            if (letter, group) in {(g[0], g[1:]) for g in groups}:
                raise _Refused(Error.MODAL_GROUP_VIOLATION)
            groups.add(letter + group)
            (gcodes if letter == "G" else mcodes).append(code)
        elif letter in _VALUE_WORDS:
            if letter in values:
                raise _Refused(Error.WORD_REPEATED)
            values[letter] = value
        else:
            raise _Refused(Error.UNSUPPORTED_COMMAND)
    gset = set(gcodes)
    if jog:
        if mcodes or not gset <= _JOG_G or set(values) - set("XYZFN"):
            raise _Refused(Error.INVALID_JOG_COMMAND)
        if "F" not in values:
            raise _Refused(Error.UNDEFINED_FEED_RATE)
    m.line = 0  # gc_block.values.n: the line's own N word, 0 without one
    if "N" in values:
        n = values["N"]
        if n < 0 or n > 10_000_000 or n != int(n):
            raise _Refused(Error.INVALID_LINE_NUMBER)
        m.line = int(n)
    axes = {a.lower(): v for a, v in values.items() if a in "XYZ"}
    out = Executed()

    # Execution order of gc_execute_block: feed mode, feed, spindle, tool, spindle/coolant
    # state, dwell, plane, units, distance, coordinate system, non-modal, motion, stop.
    if 93 in gset or 94 in gset:
        m.inverse_time = 93 in gset
    scale = MM_PER_INCH if (20 in gset or (not m.metric and 21 not in gset)) else 1.0
    if "F" in values:
        if values["F"] < 0:
            raise _Refused(Error.NEGATIVE_VALUE)
        m.feed = values["F"] * scale
    if "S" in values:
        if values["S"] < 0:
            raise _Refused(Error.NEGATIVE_VALUE)
        m.speed = values["S"]
    if "T" in values:
        if values["T"] != int(values["T"]):
            raise _Refused(Error.COMMAND_VALUE_NOT_INTEGER)
        m.tool = int(values["T"])
    for code in mcodes:
        if code in (3.0, 4.0, 5.0):
            m.spindle = f"M{int(code)}"
        elif code == 9.0:
            m.coolant = frozenset()
        elif code in (7.0, 8.0):
            m.coolant = m.coolant | {f"M{int(code)}"}
    if 4 in gset:
        if "P" not in values:
            raise _Refused(Error.VALUE_WORD_MISSING)
        if values["P"] < 0:
            raise _Refused(Error.NEGATIVE_VALUE)
        out = replace(out, dwell=values["P"])
    for plane in (17, 18, 19):
        if plane in gset:
            m.plane = plane
    if 20 in gset or 21 in gset:
        m.metric = 21 in gset
    if 90 in gset or 91 in gset:
        m.absolute = 90 in gset
    for g in (54, 55, 56, 57, 58, 59):
        if g in gset:
            if m.coord != g - 54:
                out = replace(out, offsets_changed=True)
            m.coord = g - 54

    axes_taken = False
    mm = {a: v * scale for a, v in axes.items()}
    if 10 in gset:
        _g10(m, values, mm)
        axes_taken = True
        out = replace(out, offsets_changed=True, stores=True)
    elif 92.0 in gset:
        if not axes:
            raise _Refused(Error.NO_AXIS_WORDS)
        for a, v in mm.items():
            # gcode.c: the tool length offset is taken out of G92's value too (line 571).
            m.g92[a] = m.position[a] - m.wcs[m.coord][a] - v - (m.tlo if a == "z" else 0.0)
        axes_taken = True
        out = replace(out, offsets_changed=True)
    elif 92.1 in gset:
        m.g92 = dict.fromkeys(AXES, 0.0)
        out = replace(out, offsets_changed=True)

    if 43.1 in gset:
        # gcode.c line 495: the Z word alone; the offset is the value (line 990).
        if set(axes) != {"z"}:
            raise _Refused(Error.G43_DYNAMIC_AXIS_ERROR)
        m.tlo = mm["z"]
        axes_taken = True
        out = replace(out, offsets_changed=True)
    elif 49.0 in gset:
        m.tlo = 0.0  # gcode.c line 987
        out = replace(out, offsets_changed=True)

    motion_codes = [g for g in gcodes if _G_GROUP[g] == "motion"]
    if motion_codes:
        m.motion = motion_codes[0]
        # A motion word in the block is a motion command with or without axes (gcode.c:167),
        # and every mode but G0 and G80 needs a feed defined by then (:664), even one
        # that moves nothing (`G1 M3 S100` on a board that has had no F: error:22).
        if m.motion not in (0.0, 80.0) and m.feed <= 0:
            raise _Refused(Error.UNDEFINED_FEED_RATE)
    if jog:
        m.motion = 1.0
    if axes and not axes_taken:
        if m.motion == 80:
            raise _Refused(Error.AXIS_WORDS_EXIST)
        target = dict(m.position)
        wco = m.wco()
        for a, v in mm.items():
            if 53 in gset:
                target[a] = v
            elif m.absolute:
                target[a] = v + wco[a]
            else:
                target[a] = m.position[a] + v
        if 53 in gset and m.motion not in (0.0, 1.0):
            raise _Refused(Error.G53_INVALID_MOTION_MODE)
        rapid = m.motion == 0.0
        if not rapid and m.feed <= 0:
            raise _Refused(Error.UNDEFINED_FEED_RATE)
        if jog and not travel_ok(target):
            raise _Refused(Error.TRAVEL_EXCEEDED)
        arc = _arc(m, target, values, scale) if m.motion in (2.0, 3.0) else None
        move = Move(target, m.feed, m.line, rapid, arc, m.spindle, m.speed)
        if m.motion in _PROBES:
            if m.feed <= 0:
                raise _Refused(Error.UNDEFINED_FEED_RATE)
            toward, alarm = _PROBES[m.motion]
            out = replace(out, probe=Probe(move, toward, alarm))
        else:
            out = replace(out, moves=(move,))
            m.position = target
    elif m.motion in _PROBES and motion_codes:
        raise _Refused(Error.NO_AXIS_WORDS)

    for code in mcodes:
        if code in (0.0, 1.0, 2.0, 30.0):
            stop = "M30" if code == 30 else f"M{int(code)}"
            if code == 0.0:
                m.program_flow = stop  # shown in [GC:] while paused
            out = replace(out, stop=stop)
            if code in (2.0, 30.0):
                m.program_end()
    return out


def _g10(m: Modal, values: dict[str, float], mm: dict[str, float]) -> None:
    """G10 L2 Pn (set offset) and L20 Pn (make the current position read as given)."""
    if "L" not in values or "P" not in values:
        raise _Refused(Error.VALUE_WORD_MISSING)
    p = values["P"]
    if p != int(p) or not 0 <= p <= 6 or values["L"] not in (2.0, 20.0):
        raise _Refused(Error.UNSUPPORTED_COMMAND)
    index = m.coord if p == 0 else int(p) - 1
    for a, v in mm.items():
        if values["L"] == 2.0:
            m.wcs[index][a] = v
        else:
            m.wcs[index][a] = m.position[a] - m.g92[a] - v


def _arc(m: Modal, target: dict[str, float], values: dict[str, float], scale: float) -> Arc:
    first, second, off1, off2 = _PLANES[m.plane]
    x0, y0 = m.position[first], m.position[second]
    x1, y1 = target[first], target[second]
    clockwise = m.motion == 2.0
    if "R" in values:
        radius = values["R"] * scale
        dx, dy = x1 - x0, y1 - y0
        chord = math.hypot(dx, dy)
        if chord == 0:
            raise _Refused(Error.INVALID_TARGET)
        h2 = 4 * radius * radius - chord * chord
        if h2 < -1e-6:
            raise _Refused(Error.ARC_RADIUS_ERROR)
        h = -math.sqrt(max(h2, 0.0)) / chord
        if not clockwise:
            h = -h
        if radius < 0:
            h, radius = -h, -radius
        cx, cy = x0 + 0.5 * (dx - dy * h), y0 + 0.5 * (dy + dx * h)
    elif off1 in values or off2 in values:
        cx = x0 + values.get(off1, 0.0) * scale
        cy = y0 + values.get(off2, 0.0) * scale
        radius = math.hypot(x0 - cx, y0 - cy)
        if abs(radius - math.hypot(x1 - cx, y1 - cy)) > max(0.005, 0.001 * radius):
            raise _Refused(Error.INVALID_TARGET)
    else:
        raise _Refused(Error.NO_AXIS_WORDS_IN_PLANE)
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
