"""A program's tool changes: where its `M6`s are, which tool each asks for, and the
line without its `M6` (issue 29).

Pure text work on lines as `program_lines` gives them (comments stripped), each
in linear time: every pattern is a letter, optional blanks and digits, with no
two parts that could match the same characters.

- `has_m6(text)`: whether the line holds an `M6` (also `M06`, `m 6`; not
  `M60`, `M61` or `M6.1`).
- `tool_words(text)`: the T words on the line (the tool selected).
- `without_m6(text)`: the line with its `M6` word removed ("" when nothing else
  was on it but an N word).

Which dialect sends what after the host handled a change is the session's
(`SessionBase.tool_change_line`); what the machine does at one is
hostd/machine/toolchange.py.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

# M, blanks, leading zeros, 6, not followed by another digit or a decimal point.
_M6 = re.compile(r"[mM][ \t]*+0*+6(?![0-9.])")
_T = re.compile(r"[tT][ \t]*+([0-9]++)")
_ONLY_N = re.compile(r"[nN][ \t]*+[0-9]*+[ \t]*+")
POLICIES = ("pause", "probe", "ignore", "refuse")
# The modes a measurement (or the operator's lines) between the program's lines may
# change, and must give back: units (G20/G21), distance (G90/G91, not the arc modes
# G90.1/G91.1), the feed (F), and the motion mode, plane and coordinate system.
# A G word: its number, read in one pass (possessive, no two parts on the same digits).
_G = re.compile(r"[gG][ \t]*+([0-9]++(?:\.[0-9]*+)?)")
_F = re.compile(r"[fF][ \t]*+([0-9]*+\.?[0-9]*+)")
_UNITS = frozenset({"G20", "G21"})
_DISTANCE = frozenset({"G90", "G91"})
_PLANES = frozenset({"G17", "G18", "G19"})
_WCS = frozenset({"G54", "G55", "G56", "G57", "G58", "G59", "G59.1", "G59.2", "G59.3"})
_MOTIONS = frozenset({"G0", "G1", "G2", "G3", "G38.2", "G38.3", "G38.4", "G38.5", "G80"})
# The motion mode put back: a line of G0, G1 or G80 alone selects it and moves nothing
# (gnea/grbl gcode.c:658,670 "Axis words are optional"; g2core cm_straight_traverse and
# cm_straight_feed set the mode, then return on no axis word). An arc or a probe cannot
# be selected without a move (gcode.c:682 "No axis words": error), so G1 stands in for
# G2/G3 (a feed, never a rapid), and a G38.x in force is not put back.
_MOTION_BACK = {"G0": "G0", "G1": "G1", "G80": "G80", "G2": "G1", "G3": "G1"}
# The spindle's state (M3 CW, M4 CCW, M5 off; M30 and the like are not it) and speed (S).
_SPINDLE = re.compile(r"[mM][ \t]*+0*+([345])(?![0-9.])")
_S = re.compile(r"[sS][ \t]*+([0-9]*+\.?[0-9]*+)")


def _g(number: str) -> str:
    """`00` is G0, `38.20` is G38.2, `59.1` is G59.1: the code as the tables name it."""
    whole, _, fraction = number.partition(".")
    whole = whole.lstrip("0") or "0"
    fraction = fraction.rstrip("0")
    return f"G{whole}.{fraction}" if fraction else f"G{whole}"


def has_m6(text: str) -> bool:
    """The line holds an M6 (a tool change)."""
    return ("M" in text or "m" in text) and _M6.search(text) is not None


def tool_words(text: str) -> list[int]:
    """The numbers of the line's T words, in order."""
    if "T" not in text and "t" not in text:
        return []
    return [int(found) for found in _T.findall(text)]


def without_m6(text: str) -> str:
    """The line with its M6 words removed and blanks tidied; "" when nothing is left
    but an N word (a line number alone is no block worth sending)."""
    rest = " ".join(_M6.sub(" ", text).split())
    return "" if not rest or _ONLY_N.fullmatch(rest) else rest


@dataclass(frozen=True, slots=True)
class Modes:
    """The program's units, distance mode, feed and spindle where it stands (as its
    words say)."""

    units: str = "G21"
    distance: str = "G90"
    feed: str | None = None  # the F word's number as written, in the program's units
    spindle: str = "M5"  # M3, M4 or M5
    speed: str | None = None  # the S word's number as written
    # As the program's words set them; None where they never did (the board's own).
    motion: str | None = None  # G0, G1, G2, G3, G38.x or G80
    plane: str | None = None  # G17, G18 or G19
    wcs: str | None = None  # G54 .. G59.3

    def after(self, text: str) -> Modes:
        """These modes once `text` has run."""
        units, distance, feed = self.units, self.distance, self.feed
        spindle, speed = self.spindle, self.speed
        motion, plane, wcs = self.motion, self.plane, self.wcs
        if "G" in text or "g" in text:
            for number in _G.findall(text):
                code = _g(number)
                if code in _UNITS:
                    units = code
                elif code in _DISTANCE:
                    distance = code
                elif code in _MOTIONS:
                    motion = code
                elif code in _PLANES:
                    plane = code
                elif code in _WCS:
                    wcs = code
        if "F" in text or "f" in text:
            for number in _F.findall(text):
                if number not in ("", "."):
                    feed = number
        if "M" in text or "m" in text:
            for code in _SPINDLE.findall(text):
                spindle = "M" + code
        if "S" in text or "s" in text:
            for number in _S.findall(text):
                if number not in ("", "."):
                    speed = number
        return Modes(units, distance, feed, spindle, speed, motion, plane, wcs)

    def lines(self) -> list[str]:
        """The line that puts these modes back on the board, moving nothing: units,
        distance, plane and coordinate system, the motion mode (`_MOTION_BACK`), feed."""
        words = [self.units, self.distance]
        words += [code for code in (self.plane, self.wcs) if code is not None]
        back = _MOTION_BACK.get(self.motion or "")
        if back is not None:
            words.append(back)
        if self.feed is not None:
            words.append(f"F{self.feed}")
        return [" ".join(words)]

    @property
    def spinning(self) -> bool:
        """The program had the spindle on (M3 or M4)."""
        return self.spindle != "M5"

    def spindle_lines(self, dwell: float) -> list[str]:
        """The lines that turn the spindle back on as the program had it, then give it
        `dwell` seconds to reach its speed (none: no dwell); nothing if it was off."""
        if not self.spinning:
            return []
        on = self.spindle + (f" S{self.speed}" if self.speed is not None else "")
        if dwell <= 0:
            return [on]
        return [on, f"G4 P{dwell:.3f}".rstrip("0").rstrip(".")]
