"""The modal-state model: G-code lines in, modal state out. No I/O, O(1) memory.

`GcodeModel.step(line)` reads one line of a file as the controller would, in
RS274/NGC's order of execution within a block, and keeps what it changes:
the modes, F S T, coolant, offsets and the position. `state()` is a snapshot;
`ModalState.preamble()` the G-code to restore it. Where controllers differ
the `Dialect` decides (dialects.py, docs/gcode.md).

What the file alone cannot tell is None in the snapshot and NaN inside: the
position before the first absolute move (unless a start is given), the G28/G30
home positions and the G54.. offsets (unless given, from the machine's
settings), the position after a probe (G38.x), a canned cycle, or a tool
length offset change (G43/G49: the offset is the machine's).

Not modelled, and warned about: parameters and expressions (`#1`, `[1+2]`),
O-word subroutines and loops, cutter compensation (G41/G42: the path is offset
from the programmed one), canned cycles (G81-G89), G10 L1/L10/L11 (tool table),
rotation (G10 R). The model then keeps going, as the controller would with
whatever it can read.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

from hostd.protocol.gcodestate.dialects import G2CORE, Dialect
from hostd.protocol.gcodestate.state import AXES, MM_PER_INCH, WCS, ModalState
from hostd.protocol.gcodewords import (
    INTEGER_DIGITS,
    not_a_number,
    read_words,
    strip_comments,
    too_long,
)

NAN = math.nan
DEFAULT_RAPID = 5000.0  # mm/min: a rapid's speed when the machine's is not known
_AXIS = {"X": 0, "Y": 1, "Z": 2, "A": 3, "B": 4, "C": 5}
_LINEAR = 3  # axes below this index are lengths; A B C are degrees, never scaled
_PARAMS = frozenset("DEFHIJKLPQRS")
# Plane -> (first axis, second axis, helix axis, the two offset letters), LinuxCNC's order.
_PLANES = {"G17": (0, 1, 2, "I", "J"), "G18": (2, 0, 1, "K", "I"), "G19": (1, 2, 0, "J", "K")}
_WCS_INDEX = {name: i for i, name in enumerate(WCS)}

_G_MOTION = frozenset(
    {"G0", "G1", "G2", "G3", "G38.2", "G38.3", "G38.4", "G38.5", "G80"}
    | {f"G{n}" for n in range(81, 90)}
)
_G_NONMODAL = frozenset(
    {"G10", "G28", "G28.1", "G28.2", "G28.3", "G30", "G30.1", "G92", "G92.1", "G92.2", "G92.3"}
)
# Modal groups the model only records; their codes and what they set.
_G_SIMPLE = {
    "G17": "plane",
    "G18": "plane",
    "G19": "plane",
    "G20": "units",
    "G21": "units",
    "G90": "distance",
    "G91": "distance",
    "G90.1": "arc_distance",
    "G91.1": "arc_distance",
    "G93": "feed_mode",
    "G94": "feed_mode",
    "G95": "feed_mode",
    "G61": "path",
    "G61.1": "path",
    "G64": "path",
}
# Accepted without an effect on the model.
_G_QUIET = frozenset({"G4", "G40", "G53", "G98", "G99", "G43", "G43.1", "G49"})
_M_KNOWN = frozenset(
    {"M0", "M1", "M2", "M3", "M4", "M5", "M6", "M7", "M8", "M9", "M30", "M60", "M61"}
    | {"M48", "M49", "M50", "M51", "M52", "M53"}
)
# Memory bounds: a file of a million lines each spelling a G code its own way
# (`G1.000001`, `G1.000002`...) or naming its own tool must not grow the analysis.
CODE_CACHE_SIZE = 4096  # spellings of codes kept (`G01` -> `G1`); a real file uses dozens
MAX_WARNINGS = 100  # distinct warning texts; the rest are counted under one
MAX_TOOLS = 1000  # distinct T numbers listed
_CODE_CACHE: dict[tuple[str, str], str] = {}
MORE_WARNINGS = f"more warnings of other kinds: only the first {MAX_WARNINGS} are listed"


def unsupported_text(code: str, dialect: str) -> str:
    """The warning for a code the dialect lacks. Named so that a caller that decides a
    code itself (preflight.py: the machine's tool_change policy decides M6) can find it."""
    return f"{code} is not supported by {dialect}"


class ProgramError(Exception):
    """A line no board may run as the file wrote it: the analysis stops and says where.

    `line` is the file's line number (1-based). Today: a number with more integer
    digits than a board reads (it wraps past 2**31; Python reads 400 nines as
    infinity, which a preamble would have sent as `Finf`), or one spelled `inf`/`nan`.
    """

    def __init__(self, line: int, message: str) -> None:
        super().__init__(line, message)  # both in args: it is pickled back from a worker
        self.line = line
        self.message = message

    def __str__(self) -> str:
        return f"line {self.line}: {self.message}"


def _code(letter: str, number: str) -> str:
    """`G01` -> `G1`, `G38.20` -> `G38.2`: one spelling for each code."""
    key = (letter, number)
    code = _CODE_CACHE.get(key)
    if code is None:
        code = f"{letter}{float(number):g}"
        if len(_CODE_CACHE) >= CODE_CACHE_SIZE:
            _CODE_CACHE.clear()  # bounded: a hostile file only costs the cache its hits
        _CODE_CACHE[key] = code
    return code


class GcodeModel:
    """Reads a G-code file line by line and keeps the controller's modal state.

    `start`: the machine position (mm, machine coordinates) before the file, None
    for unknown. `offsets`: known coordinate-system offsets (mm), e.g. read from the
    board; `homes`: the stored G28/G30 positions (mm, machine coordinates). Axes left
    out are unknown, and so is every position computed from them.
    `track_bounds` collects the extent of every move (analysis.py).
    `g92`: the G92 offset in force before the file (mm; none: zero).
    `keep_offsets`: the offsets given are the board's as it holds them now, and a G10
    in the file does not change them in the model (a resume: the board stored what the
    file's G10 wrote when the job ran it); what the file wrote is kept in `wcs_file`.
    """

    def __init__(
        self,
        dialect: Dialect = G2CORE,
        *,
        start: Mapping[str, float] | None = None,
        offsets: Mapping[str, Mapping[str, float]] | None = None,
        homes: Mapping[str, Mapping[str, float]] | None = None,
        units: str = "G21",
        motion: str = "G80",
        block_delete: bool = False,
        track_bounds: bool = False,
        velocity: Mapping[str, float] | None = None,
        acceleration: Mapping[str, float] | None = None,
        keep_offsets: bool = False,
        g92: Mapping[str, float] | None = None,
    ) -> None:
        self.dialect = dialect
        self.keep_offsets = keep_offsets
        self.block_delete = block_delete
        self.line = 0
        self.n: int | None = None
        self.units = units
        self.scale = MM_PER_INCH if units == "G20" else 1.0
        self.distance = "G90"
        self.arc_distance = "G91.1"
        self.plane = "G17"
        self.wcs = 0
        self.feed_mode = "G94"
        self.feed: float | None = None  # the F number as the file wrote it
        self.feed_scale = self.scale  # mm per unit of the units F was written in
        self.motion = motion
        self.path = "G64"
        self.spindle = "M5"
        self.speed: float | None = None
        self.mist = False
        self.flood = False
        self.tool: int | None = None
        self.selected_tool: int | None = None
        self.tool_length = "G49"
        # The tool length offset in force (mm, Z): 0 under G49, G43.1's Z, unknown (NaN)
        # under G43 (the machine's tool table); `tool_h` is G43's H word.
        self.tlo = 0.0
        self.tool_h: int | None = None
        # The feed (mm/min, G94) of the last feed move along Z alone: how the file plunges.
        self.plunge_feed: float | None = None
        self.ended = False
        self.pos = [_get(start, a) for a in AXES]
        self.wcs_offsets = [[_get((offsets or {}).get(w), a) for a in AXES] for w in WCS]
        self.wcs_set: list[set[int]] = [set() for _ in WCS]
        self.wcs_file = [[NAN] * 6 for _ in WCS]  # what the file's G10 wrote (keep_offsets)
        self.g10_line: int | None = None  # the last line whose G10 L2/L20 set an offset
        self.g53_line: int | None = None  # the last line with a G53 move
        self.g92_line: int | None = None  # the last line with a G92, G92.1, G92.2 or G92.3
        self.g92 = [float((g92 or {}).get(a, 0.0)) for a in AXES]  # in force before the file
        self.g92_on = any(self.g92)
        self.homes = {
            "G28": [_get((homes or {}).get("G28"), a) for a in AXES],
            "G30": [_get((homes or {}).get("G30"), a) for a in AXES],
        }
        # Figures for the analysis, gathered in the same pass.
        self.blocks = 0
        self.rapids = 0
        self.feeds = 0
        self.arcs = 0
        self.units_seen: set[str] = set()
        self.tools: set[int] = set()
        self.max_speed: float | None = None
        self.warnings: dict[str, tuple[int, int]] = {}  # text -> (first line, count)
        self.track_bounds = track_bounds
        self.low = [math.inf] * 6
        self.high = [-math.inf] * 6
        self.low_at = [0] * 6  # the file line that went furthest, each way (travel errors)
        self.high_at = [0] * 6
        self.moved: set[int] = set()  # axes named in a move
        # The estimate (with `track_bounds`): seconds of motion and dwell. Axis speed limits
        # in mm/min (a rapid runs at them; DEFAULT_RAPID where not known), accelerations in
        # mm/s^2 (none known: moves take length / speed).
        self.seconds = 0.0
        self.vmax = [float((velocity or {}).get(a, 0.0)) for a in AXES]
        self.amax = [float((acceleration or {}).get(a, 0.0)) for a in AXES]
        self._direction: tuple[float, float, float] | None = None
        self._arc_length = 0.0

    # --- reading -----------------------------------------------------------------

    def feed_lines(self, lines: Iterable[str]) -> GcodeModel:
        for text in lines:
            self.step(text)
        return self

    def step(self, text: str) -> None:
        """Read one line of the file (its number is the count of lines read)."""
        self.line += 1
        if "(" in text or ";" in text:
            text, unclosed = strip_comments(text)
            if unclosed:
                self.warn("an unclosed comment: the rest of the line is ignored")
        text = text.strip()
        if not text:
            return
        first = text[0]
        if first == "%":
            return
        if first == "/":
            if self.block_delete:
                return
            text = text[1:]
        text = text.upper()
        words, end = read_words(text)
        if end != len(text):
            self._unreadable(text, end)
            return
        wide = too_long(words, text)
        if wide is not None:
            letter, number = wide
            shown = number if len(number) <= 16 else f"{number[:12]}...({len(number)} characters)"
            raise ProgramError(
                self.line,
                f"the number of {letter}{shown} has more than {INTEGER_DIGITS} integer digits: "
                "no board reads it (they wrap past 2,147,483,647)",
            )
        self.blocks += 1
        self._block(words)

    def _unreadable(self, text: str, at: int) -> None:
        if not_a_number(text, at):
            raise ProgramError(
                self.line,
                f"{text[at : at + 8]!r}: a number spelled inf or nan, which no board reads",
            )
        if text[0] == "O":
            self.warn("O-word subroutines and loops are not modelled")
        elif "#" in text or "[" in text:
            self.warn("parameters and expressions are not modelled: the line is ignored")
        else:
            self.warn("an unreadable line is ignored")

    def warn(self, text: str) -> None:
        seen = self.warnings.get(text)
        if seen is None and len(self.warnings) >= MAX_WARNINGS:
            text = MORE_WARNINGS
            seen = self.warnings.get(text)
        self.warnings[text] = (self.line, 1) if seen is None else (seen[0], seen[1] + 1)

    # --- one block, in RS274/NGC's order of execution ---------------------------------

    def _block(self, words: list[tuple[str, str]]) -> None:
        gcodes: list[str] = []
        mcodes: list[str] = []
        axes: dict[int, float] = {}
        params: dict[str, float] = {}
        for letter, number in words:
            if letter == "G":
                gcodes.append(_code("G", number))
            elif letter in _AXIS:
                axes[_AXIS[letter]] = float(number)
            elif letter == "M":
                mcodes.append(_code("M", number))
            elif letter == "N":
                self.n = int(float(number))
            elif letter in _PARAMS or letter == "T":
                params[letter] = float(number)
            else:
                self.warn(f"unsupported word {letter}")
        motion = None
        nonmodal = None
        machine = False
        for g in gcodes:
            if g in _G_MOTION:
                motion = g
            elif g in _G_SIMPLE:
                if g in self.dialect.unsupported:
                    self.warn(f"{g} is not supported by {self.dialect.name}")
                    continue
                if g in ("G20", "G21") and self.dialect.feed_before_units and "F" in params:
                    self._set_feed(params.pop("F"))
                setattr(self, _G_SIMPLE[g], g)
                if g in ("G20", "G21"):
                    self.scale = MM_PER_INCH if g == "G20" else 1.0
                    self.units_seen.add(g)
            elif g in _WCS_INDEX:
                self.wcs = _WCS_INDEX[g]
            elif g in _G_NONMODAL:
                nonmodal = g
            elif g == "G53":
                machine = True
            elif g in ("G43", "G43.1", "G49"):
                self._tool_length(g, axes, params)
            elif g in ("G41", "G42"):
                self.warn(f"{g} cutter compensation is not modelled: positions are the program's")
            elif g not in _G_QUIET:
                self.warn(f"{g} is not supported")
            if g in self.dialect.unsupported and g not in _G_SIMPLE:
                self.warn(f"{g} is not supported by {self.dialect.name}")
        if params:
            self._words(params)
            if "G4" in gcodes and self.track_bounds:
                self.seconds += max(params.get("P", 0.0), 0.0)
                self._direction = None  # a stop
        if mcodes:
            self._mcodes_before(mcodes, params)
        if "G43.1" in gcodes:
            axes = {}  # G43.1's axis words are the offset, not a move
        if nonmodal is not None:
            self._nonmodal(nonmodal, axes, params)
        elif motion is not None or axes or ("I" in params or "J" in params or "K" in params):
            if motion is not None:
                self.motion = motion
            if axes:
                self._move(axes, params, machine)
            elif self.motion in ("G2", "G3") and any(k in params for k in _PLANES[self.plane][3:]):
                self._move(axes, params, machine)  # a full circle: I/J/K and no end point
        if mcodes:
            for m in mcodes:
                if m in ("M2", "M30"):
                    self._program_end()

    def _tool_length(self, g: str, axes: dict[int, float], params: dict[str, float]) -> None:
        """G43 Hn (the machine's table: unknown here), G43.1 Z (the file's), G49 (none).

        The model's position is the programmed point, the machine's minus the offset:
        when the offset changes, the machine stays, so the programmed point moves by it.
        """
        h = int(params["H"]) if "H" in params else self.tool
        if g == self.tool_length and g != "G43.1" and (g == "G49" or h == self.tool_h):
            return  # the same offset again: nothing moves
        if g == "G49":
            tlo = 0.0
            self.tool_h = None
        elif g == "G43.1":
            tlo = axes.get(2, 0.0) * self.scale
            for i in axes:
                if i != 2:
                    self.warn("G43.1 on an axis other than Z is not modelled")
        else:
            tlo = NAN
            self.tool_h = h
        self.pos[2] += self.tlo - tlo
        self.tlo = tlo
        self.tool_length = g

    def _set_feed(self, value: float) -> None:
        self.feed = value
        self.feed_scale = self.scale

    def _words(self, params: dict[str, float]) -> None:
        f = params.get("F")
        if f is not None:
            self._set_feed(f)
        s = params.get("S")
        if s is not None:
            self.speed = s
            if self.max_speed is None or s > self.max_speed:
                self.max_speed = s
        t = params.get("T")
        if t is not None:
            self.selected_tool = int(t)
            if len(self.tools) < MAX_TOOLS:
                self.tools.add(int(t))

    def _mcodes_before(self, mcodes: list[str], params: dict[str, float]) -> None:
        for m in mcodes:
            if m in self.dialect.unsupported:
                self.warn(unsupported_text(m, self.dialect.name))
            elif m == "M6":
                self.tool = self.selected_tool
            elif m == "M61" and "Q" in params:
                self.tool = int(params["Q"])
            elif m in ("M3", "M4", "M5"):
                self.spindle = m
            elif m == "M7":
                self.mist = True
            elif m == "M8":
                self.flood = True
            elif m == "M9":
                self.mist = self.flood = False
            elif m not in _M_KNOWN:
                self.warn(f"{m} is not supported")

    def _program_end(self) -> None:
        """M2/M30 as the dialect does it (RS274/NGC 3.6.1, with each controller's changes)."""
        d = self.dialect
        self.ended = True
        self.wcs = 0
        self.plane = "G17"
        self.distance = "G90"
        self.feed_mode = "G94"
        self.spindle = "M5"
        self.mist = self.flood = False
        self.motion = d.end_motion
        if d.end_clears_g92:
            self.g92_on = False
        if d.end_zeroes_feed:
            self.feed = 0.0
        if d.end_resets_arc_distance:
            self.arc_distance = "G91.1"

    # --- group 0: G10, G28, G30, G92 ------------------------------------------------

    def _nonmodal(self, g: str, axes: dict[int, float], params: dict[str, float]) -> None:
        if g.startswith("G92"):
            self.g92_line = self.line
        if g == "G10":
            self._g10(axes, params)
        elif g in ("G28", "G30"):
            home = self.homes[g]
            if axes:
                self._move(axes, params, False, rapid=True)
            moving = axes if (axes and self.dialect.home_only_named_axes) else range(6)
            for i in moving:
                self.pos[i] = home[i]
            self.rapids += 1
            if self.track_bounds:
                self._extend_line()
            if any(math.isnan(home[i]) for i in moving):
                self.warn(f"{g}: its stored position is the machine's, not known from the file")
        elif g in ("G28.1", "G30.1"):
            self.homes[g[:3]] = list(self.pos)
        elif g == "G28.2":
            for i in axes or range(3):
                self.pos[i] = NAN  # homed: where is the machine's setting
        elif g == "G28.3":
            for i, v in axes.items():
                self.pos[i] = v * self._axis_scale(i)
        elif g == "G92":
            offset = self.wcs_offsets[self.wcs]
            current = self._g92_now()
            self.g92 = current
            for i, v in axes.items():
                self.g92[i] = self.pos[i] - offset[i] - v * self._axis_scale(i)
            self.g92_on = True
        elif g == "G92.1":
            self.g92 = [0.0] * 6
            self.g92_on = False
        elif g == "G92.2":
            self.g92_on = False
        elif g == "G92.3":
            self.g92_on = True

    def _g10(self, axes: dict[int, float], params: dict[str, float]) -> None:
        l_word = params.get("L")
        p = int(params.get("P", 0))
        if l_word not in (2.0, 20.0):
            self.warn("G10 other than L2/L20 (tool table) is not modelled")
            return
        if "R" in params:
            self.warn("G10 R (rotation) is not modelled")
        index = self.wcs if p == 0 else p - 1
        if not 0 <= index < len(WCS):
            self.warn(f"G10 P{p}: no such coordinate system")
            return
        offset = self.wcs_file[index] if self.keep_offsets else self.wcs_offsets[index]
        g92 = self._g92_now() if self.dialect.l20_uses_g92 else [0.0] * 6
        for i, v in axes.items():
            value = v * self._axis_scale(i)
            offset[i] = value if l_word == 2.0 else self.pos[i] - g92[i] - value
            self.wcs_set[index].add(i)
        if axes:
            self.g10_line = self.line

    # --- motion ------------------------------------------------------------------

    def _axis_scale(self, i: int) -> float:
        return self.scale if i < _LINEAR else 1.0

    def _g92_now(self) -> list[float]:
        return list(self.g92) if self.g92_on else [0.0] * 6

    def _move(
        self, axes: dict[int, float], params: dict[str, float], machine: bool, rapid: bool = False
    ) -> None:
        """Move to `axes` (program words) in the current motion mode (or a rapid for G28)."""
        pos = self.pos
        start = list(pos)
        scale = self.scale
        self.moved.update(axes)
        if machine:
            self.g53_line = self.line
            for i, v in axes.items():
                pos[i] = v * scale if i < _LINEAR else v
            if 2 in axes:
                pos[2] -= self.tlo  # G53 ignores the tool length offset: the machine's Z
        elif self.distance == "G90":
            offset = self.wcs_offsets[self.wcs]
            g92 = self.g92 if self.g92_on else None
            for i, v in axes.items():
                base = offset[i] + g92[i] if g92 else offset[i]
                pos[i] = (v * scale if i < _LINEAR else v) + base
        else:
            for i, v in axes.items():
                pos[i] += v * scale if i < _LINEAR else v
        motion = "G0" if rapid else self.motion
        if motion == "G0":
            self.rapids += 1
        elif motion == "G1":
            self.feeds += 1
            if not rapid and set(axes) == {2} and self.feed_mode == "G94" and self.feed:
                self.plunge_feed = self.feed * self.feed_scale
        elif motion in ("G2", "G3"):
            self.feeds += 1
            self.arcs += 1
            self._arc(start, params, motion == "G2")
            if self.track_bounds:
                self._time(start, False, self._arc_length)
            return
        elif motion == "G80":
            self.warn("axis words with no motion mode (G80)")
            pos[:] = start
            return
        else:
            self.feeds += 1
            self._unknown_end(motion, axes)
        if self.track_bounds:
            self._extend_line()
            self._time(start, motion == "G0", None)

    def _time(self, start: list[float], rapid: bool, length: float | None) -> None:
        """Add the move's duration: its length at its speed, capped by each axis's limit,
        plus, where accelerations are known, the time lost slowing down for the corner
        before it (none on a straight continuation, a full stop on a reversal)."""
        d = [self.pos[i] - start[i] for i in range(3)]
        chord = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        if length is None:
            length = chord
        if not length or math.isnan(length):
            return
        cap = math.inf
        accel = math.inf
        if chord:
            unit = (d[0] / chord, d[1] / chord, d[2] / chord)
            for i in range(3):
                share = abs(unit[i])
                if share > 1e-9:
                    if self.vmax[i]:
                        cap = min(cap, self.vmax[i] / share)
                    if self.amax[i]:
                        accel = min(accel, self.amax[i] / share)
        else:
            unit = self._direction or (0.0, 0.0, 0.0)
        if self.feed_mode == "G93" and not rapid:
            if self.feed:
                self.seconds += 60.0 / self.feed
            self._direction = unit
            return
        if rapid:
            speed = cap if math.isfinite(cap) else DEFAULT_RAPID
        else:
            feed = (self.feed or 0.0) * self.feed_scale
            if feed <= 0:
                return  # refused by the controller: no F
            speed = min(feed, cap)
        self.seconds += 60.0 * length / speed
        if math.isfinite(accel):
            before = self._direction
            turn = 1.0
            if before is not None:
                turn = (1 - before[0] * unit[0] - before[1] * unit[1] - before[2] * unit[2]) / 2
            self.seconds += turn * (speed / 60.0) / accel
        self._direction = unit

    def _unknown_end(self, motion: str, axes: dict[int, float]) -> None:
        if motion.startswith("G38"):
            self.warn(f"{motion} probing: the position afterwards is where the probe stopped")
            for i in axes:
                self.pos[i] = NAN
        else:
            self.warn(f"{motion} canned cycles are not modelled: Z is unknown afterwards")
            self.pos[2] = NAN

    def _extend_line(self) -> None:
        low, high = self.low, self.high
        for i, v in enumerate(self.pos):
            if v < low[i]:
                low[i] = v
                self.low_at[i] = self.line
            if v > high[i]:
                high[i] = v
                self.high_at[i] = self.line

    def _arc(self, start: list[float], params: dict[str, float], clockwise: bool) -> None:
        a, b, _, off_a, off_b = _PLANES[self.plane]
        x0, y0 = start[a], start[b]
        x1, y1 = self.pos[a], self.pos[b]
        scale = self.scale
        if "R" in params:
            radius = params["R"] * scale
            dx, dy = x1 - x0, y1 - y0
            chord = math.hypot(dx, dy)
            if chord == 0:
                self.warn("an R arc whose end is its start: refused by the controller")
                if self.track_bounds:
                    self._extend_line()
                return
            h2 = 4 * radius * radius - chord * chord
            if h2 < 0:
                self.warn("an R arc with a radius shorter than half the chord")
            h = -math.sqrt(max(h2, 0.0)) / chord
            if not clockwise:
                h = -h
            if radius < 0:
                h = -h
            cx, cy = x0 + 0.5 * (dx - dy * h), y0 + 0.5 * (dy + dx * h)
        else:
            if off_a not in params and off_b not in params:
                self.warn("an arc without the offsets of its plane")
            if self.arc_distance == "G91.1":
                cx = x0 + params.get(off_a, 0.0) * scale
                cy = y0 + params.get(off_b, 0.0) * scale
            else:
                base = self.wcs_offsets[self.wcs]
                g92 = self._g92_now()
                cx = params.get(off_a, 0.0) * scale + base[a] + g92[a]
                cy = params.get(off_b, 0.0) * scale + base[b] + g92[b]
            r0 = math.hypot(x0 - cx, y0 - cy)
            r1 = math.hypot(x1 - cx, y1 - cy)
            error = abs(r1 - r0)
            d = self.dialect
            if error > d.arc_abs_max or (error > d.arc_abs_min and error > d.arc_rel * r0):
                self.warn(
                    f"an arc that does not close: its end is off its circle by more than "
                    f"{self.dialect.name} accepts"
                )
        if self.track_bounds:
            self._extend_line()
            turns = int(params.get("P", 1))
            self._extend_arc(a, b, (x0, y0), (x1, y1), (cx, cy), clockwise, turns)
            self._arc_length = _arc_length(
                (x0, y0),
                (x1, y1),
                (cx, cy),
                clockwise,
                turns,
                self.pos[_PLANES[self.plane][2]] - start[_PLANES[self.plane][2]],
            )

    def _extend_arc(
        self,
        a: int,
        b: int,
        p0: tuple[float, float],
        p1: tuple[float, float],
        c: tuple[float, float],
        clockwise: bool,
        turns: int,
    ) -> None:
        """The arc's extreme points, where it crosses an axis through its centre."""
        cx, cy = c
        radius = math.hypot(p0[0] - cx, p0[1] - cy)
        if math.isnan(radius) or radius == 0:
            return
        a0 = math.atan2(p0[1] - cy, p0[0] - cx)
        a1 = math.atan2(p1[1] - cy, p1[0] - cx)
        sweep = (a0 - a1) if clockwise else (a1 - a0)
        sweep %= 2 * math.pi
        if sweep < 1e-12:
            sweep = 2 * math.pi  # a full circle
        sweep += 2 * math.pi * max(turns - 1, 0)
        low, high = self.low, self.high
        for k in range(4):
            angle = k * math.pi / 2
            along = ((a0 - angle) if clockwise else (angle - a0)) % (2 * math.pi)
            if along <= sweep:
                x = cx + radius * math.cos(angle)
                y = cy + radius * math.sin(angle)
                for i, v in ((a, x), (b, y)):
                    if v < low[i]:
                        low[i], self.low_at[i] = v, self.line
                    if v > high[i]:
                        high[i], self.high_at[i] = v, self.line

    # --- the snapshot ---------------------------------------------------------------

    def state(self) -> ModalState:
        g92 = self._g92_now()
        offset = self.wcs_offsets[self.wcs]
        machine = {a: _known(v) for a, v in zip(AXES, self.pos, strict=True)}
        work = {}
        for i, a in enumerate(AXES):
            v = self.pos[i] - offset[i] - g92[i]
            work[a] = _known(v / self._axis_scale(i))
        feed = self.feed
        if feed is not None and not self.dialect.feed_follows_units:
            feed = feed * self.feed_scale / self.scale
        return ModalState(
            line=self.line,
            n=self.n,
            units="G20" if self.units == "G20" else "G21",
            distance="G91" if self.distance == "G91" else "G90",
            arc_distance="G90.1" if self.arc_distance == "G90.1" else "G91.1",
            plane="G18" if self.plane == "G18" else "G19" if self.plane == "G19" else "G17",
            wcs=WCS[self.wcs],
            feed_mode="G93"
            if self.feed_mode == "G93"
            else "G95"
            if self.feed_mode == "G95"
            else "G94",
            feed=None if self.feed_mode == "G93" else feed,
            motion=self.motion,
            path="G61" if self.path == "G61" else "G61.1" if self.path == "G61.1" else "G64",
            spindle="M3" if self.spindle == "M3" else "M4" if self.spindle == "M4" else "M5",
            speed=self.speed,
            mist=self.mist,
            flood=self.flood,
            tool=self.tool,
            selected_tool=self.selected_tool,
            tool_length=self.tool_length,
            machine=machine,
            work=work,
            wcs_offsets={
                name: {a: _known(v) for a, v in zip(AXES, self.wcs_offsets[i], strict=True)}
                for i, name in enumerate(WCS)
            },
            wcs_set={
                name: tuple(AXES[i] for i in sorted(self.wcs_set[k]))
                for k, name in enumerate(WCS)
                if self.wcs_set[k]
            },
            g92={a: _known(v) for a, v in zip(AXES, g92, strict=True)},
            g92_stored={a: _known(v) for a, v in zip(AXES, self.g92, strict=True)},
            ended=self.ended,
            tlo=_known(self.tlo),
            tool_h=self.tool_h,
            plunge_feed=self.plunge_feed,
            wcs_file={
                name: {a: _known(v) for a, v in zip(AXES, self.wcs_file[i], strict=True)}
                for i, name in enumerate(WCS)
            }
            if self.keep_offsets
            else None,
            g10_line=self.g10_line,
            g53_line=self.g53_line,
        )


def _arc_length(
    p0: tuple[float, float],
    p1: tuple[float, float],
    c: tuple[float, float],
    clockwise: bool,
    turns: int,
    rise: float,
) -> float:
    """The length of a (helical) arc from p0 to p1 about c."""
    radius = math.hypot(p0[0] - c[0], p0[1] - c[1])
    a0 = math.atan2(p0[1] - c[1], p0[0] - c[0])
    a1 = math.atan2(p1[1] - c[1], p1[0] - c[0])
    sweep = ((a0 - a1) if clockwise else (a1 - a0)) % (2 * math.pi)
    if sweep < 1e-12:
        sweep = 2 * math.pi
    sweep += 2 * math.pi * max(turns - 1, 0)
    return math.hypot(radius * sweep, rise)


def _get(values: Mapping[str, float] | None, axis: str) -> float:
    if values is None or axis not in values:
        return NAN
    return float(values[axis])


def _known(value: float) -> float | None:
    return None if math.isnan(value) else value
