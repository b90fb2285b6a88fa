"""One block's effect on the modal state, in RS274/NGC's order of execution.

The layer of `GcodeModel` (model.py) above motion (motion.py): a block's words
(already read and checked by model.py) are sorted by kind, and each modal
group is applied in the order the controller applies them: F S T, the M codes
that act before motion, the tool length offset, then group 0 (G10, G28, G30,
G92) or the move, then the program end. The tables of which code belongs to
which group are here, beside the code that reads them; where controllers
differ the `Dialect` decides (dialects.py, docs/gcode.md).
"""

from __future__ import annotations

import math

from hostd.protocol.gcodestate.modes import NAN
from hostd.protocol.gcodestate.motion import _PLANES, Motion
from hostd.protocol.gcodestate.state import MM_PER_INCH, WCS

_AXIS = {"X": 0, "Y": 1, "Z": 2, "A": 3, "B": 4, "C": 5}
_PARAMS = frozenset("DEFHIJKLPQRS")
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
MAX_TOOLS = 1000  # distinct T numbers listed
_CODE_CACHE: dict[tuple[str, str], str] = {}


def unsupported_text(code: str, dialect: str) -> str:
    """The warning for a code the dialect lacks. Named so that a caller that decides a
    code itself (preflight.py: the machine's tool_change policy decides M6) can find it."""
    return f"{code} is not supported by {dialect}"


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


class Blocks(Motion):
    """Applies one block's words to the modal state (see the module docstring)."""

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
