"""Where and how to resume a program at a line: the preamble and the safe approach.

Pure: the program's lines in, a `ResumePlan` out. The modal model reads the
file up to the line before the resume line; its state is what the board must
be in when that line runs. The plan's lines are, in order:

1. the preamble (`ModalState.preamble`), with the spindle, laser and coolant
   left off, and without the codes the dialect refuses;
2. `G92.1` if the file had a G92 offset in force (it is set again at 6);
3. up to the safe height, in machine coordinates (`G53`): nothing is crossed
   at cutting depth;
4. across to the resume point in X and Y;
5. spindle or laser on at the file's speed, coolant, then a dwell for spin-up;
6. down to the start depth at the file's feed, the G92 offset set again where
   the file had it, and the distance and motion modes put back.

Every move is G90 (the file may be in G91). What the plan cannot know is said in
`uncertain`; a position it needs but cannot know is a `ResumeError`.

Positions: the model reads the file with the start unknown and every coordinate
system's offset at zero. A position is therefore known once an absolute move
has set it, and is the work position in the coordinate system the file uses;
the board keeps its own offsets (G54.. in its settings), which the approach
uses as they are.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass

from hostd.protocol.gcodestate.dialects import Dialect
from hostd.protocol.gcodestate.model import GcodeModel
from hostd.protocol.gcodestate.state import AXES, WCS, ModalState, _num

DEFAULT_DWELL = 2.0  # seconds for the spindle to reach speed before it goes down


class ResumeError(Exception):
    """The resume cannot be planned safely; the message says why and what would help."""


@dataclass(frozen=True, slots=True)
class ResumePlan:
    line: int  # the file line the job resumes at
    state: ModalState  # the modal state in force before that line
    preamble: list[str]  # what restores the state (spindle, coolant not yet on)
    approach: list[str]  # up, across, spindle on, dwell, down
    position: dict[str, float | None]  # the work position the line starts from (file units)
    uncertain: list[str]

    @property
    def lines(self) -> list[str]:
        """All that is sent before the resume line."""
        return [*self.preamble, *self.approach]

    def to_json(self) -> dict[str, object]:
        s = self.state
        return {
            "line": self.line,
            "preamble": self.preamble,
            "approach": self.approach,
            "position": self.position,
            "units": s.units,
            "wcs": s.wcs,
            "feed": s.feed,
            "spindle": s.spindle,
            "speed": s.speed,
            "tool": s.tool,
            "coolant": {"mist": s.mist, "flood": s.flood},
            "uncertain": self.uncertain,
        }


def state_before(lines: Iterable[str], line: int, dialect: Dialect) -> GcodeModel:
    """The model after reading lines 1 .. line - 1 (streamed, O(1) memory)."""
    zeros = dict.fromkeys(AXES, 0.0)
    model = GcodeModel(dialect, offsets={wcs: zeros for wcs in WCS})
    for number, text in enumerate(lines, start=1):
        if number >= line:
            break
        model.step(text)
    return model


def plan_resume(
    lines: Iterable[str],
    line: int,
    dialect: Dialect,
    *,
    safe_z: float | None,
    dwell: float = DEFAULT_DWELL,
) -> ResumePlan:
    """The plan to resume at `line`; `safe_z` is the safe height in machine coordinates (mm)."""
    model = state_before(lines, line, dialect)
    state = model.state()
    uncertain: list[str] = []
    if model.line < line - 1:
        raise ResumeError(f"the file has {model.line} lines: there is no line {line}")
    if state.ended:
        uncertain.append("the program ended (M2/M30) before this line")
    uncertain += state.unrestorable()
    uncertain += [f"{text} (first at line {first})" for text, (first, _) in model.warnings.items()]
    off = dataclasses.replace(state, spindle="M5", mist=False, flood=False)
    preamble = [_supported(text, dialect) for text in off.preamble("M6" not in dialect.unsupported)]
    preamble = [text for text in preamble if text]
    g92 = {a: v for a, v in state.g92.items() if v}
    work = dict(state.work)
    missing = [a.upper() for a in ("x", "y", "z") if work.get(a) is None]
    if missing:
        raise ResumeError(
            f"the position at line {line} is not known from the file ({', '.join(missing)}: "
            "no absolute move sets it before that line); resume at a later line, or with "
            "restore false and the machine placed by hand"
        )
    if safe_z is None:
        raise ResumeError("no safe height: set the machine's safe_z, or read its travel")
    scale = state.scale
    wx, wy, wz = (float(work[a] or 0.0) for a in ("x", "y", "z"))
    # Without the G92 offset (cleared first), the point is where the offset would put it.
    gx, gy, gz = (w + g92.get(a, 0.0) / scale for a, w in (("x", wx), ("y", wy), ("z", wz)))
    approach: list[str] = []
    if g92:
        approach.append("G92.1")
    approach.append(f"G90 G53 G0 Z{_num(safe_z / scale, 4)}")
    approach.append(f"G0 X{_num(gx, 4)} Y{_num(gy, 4)}")
    if state.spindle != "M5":
        approach.append(f"S{_num(state.speed or 0.0, 3)} {state.spindle}")
    if state.mist:
        approach.append("M7")
    if state.flood:
        approach.append("M8")
    if state.spindle != "M5" and dwell > 0:
        approach.append(f"G4 P{_num(dwell, 3)}")
    if state.feed is not None and state.feed > 0 and state.feed_mode == "G94":
        approach.append(f"G1 Z{_num(gz, 4)} F{_num(state.feed, 3)}")
    else:
        approach.append(f"G0 Z{_num(gz, 4)}")
        uncertain.append("no feed in force in G94: the tool goes down at the rapid rate")
    if g92:
        words = " ".join(f"{a.upper()}{_num(float(work[a] or 0.0), 4)}" for a in g92 if a in work)
        approach.append(f"G92 {words}")
    if state.distance == "G91":
        approach.append("G91")
    if state.motion in ("G0", "G80"):
        approach.append(state.motion)
    elif state.motion in ("G2", "G3"):
        uncertain.append(
            f"the motion mode was {state.motion}: it is G1 after the approach, so a line "
            "that continues the arc without its own G2/G3 would be a straight move"
        )
    rotary = [a.upper() for a in ("a", "b", "c") if state.work.get(a) not in (None, 0.0)]
    if rotary:
        uncertain.append(f"rotary axes ({', '.join(rotary)}) are not moved by the approach")
    uncertain.append(
        "the line the job stopped in is run again from its start: its first part is cut twice"
    )
    if any(v for v in g92.values()):
        uncertain.append("the G92 offset is set again from the file's positions (G92.1, then G92)")
    position = {a: work.get(a) for a in ("x", "y", "z")}
    return ResumePlan(line, state, preamble, approach, position, uncertain)


def _supported(text: str, dialect: Dialect) -> str:
    """A preamble line without the words the dialect refuses (grbl: G64, G90.1, M6...)."""
    words = text.split()
    kept = [w for w in words if _code(w) not in dialect.unsupported]
    return " ".join(kept)


def _code(word: str) -> str:
    letter, number = word[0], word[1:]
    try:
        return f"{letter}{float(number):g}"
    except ValueError:
        return word
