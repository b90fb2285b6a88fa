"""Where and how to resume a program at a line: the preamble and the safe approach.

Pure: the program's lines and what the board holds now in, a `ResumePlan` out.
The model reads the file up to the line before the resume line, starting from
the board's own stored offsets (G54.., its G92): its positions are then the
machine's, whatever the file did in between (G53 moves, G92, G10, G43.1). Its
state is what the board must be in when that line runs. The plan's lines are,
in order:

1. the preamble (`ModalState.preamble`): units, modes, coordinate system, tool
   and its length offset, feed; spindle, laser and coolant left off; without the
   codes the dialect refuses. It never writes an offset the board stores (G10):
   where the file wrote one, the plan says so under `uncertain`;
2. `G92.1` where the board's G92 offset is not the file's (it is set at 7);
3. up to the safe height, in machine coordinates (`G53 G0 Z`), or to the highest
   the file took the tool before the line where that is higher (its own
   clearance: a safe height set below it would cross the work);
4. across to the resume point in X and Y, in machine coordinates;
5. a spindle: on with the speed in force, coolant, a dwell for spin-up;
6. down to the start depth at the plunge feed: the file's own (its last feed
   move along Z alone before the line) or the configured one, whichever is
   slower; in machine coordinates, or in the file's own where a G43 offset from
   the machine's tool table is in force (the board adds it, as for the file);
7. a laser: on only now, in position (it moved with the beam off), no dwell;
   the G92 offset set again where the file had one; the feed, distance and
   motion modes put back.

Never `S0` with `M3`/`M4` where the file gave no speed: the board's own is
kept, and said; when the board's is known to be 0, the plan is refused.
What the plan cannot know is said in `uncertain`; a position it needs but
cannot know is a `ResumeError`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

from hostd.protocol.gcodestate.dialects import Dialect
from hostd.protocol.gcodestate.model import GcodeModel
from hostd.protocol.gcodestate.state import AXES, LINEAR, ModalState, _num

DEFAULT_DWELL = 2.0  # seconds for the spindle to reach speed before it goes down


class ResumeError(Exception):
    """The resume cannot be planned safely; the message says why and what would help."""


@dataclass(frozen=True, slots=True)
class Board:
    """What the board holds now (mm), read from it before planning.

    `offsets`: the stored G54.. offsets, by system (a system the board lacks is
    absent); `g92`: the G92 offset in force; `speed`: the spindle speed or laser
    power it would run `M3` with (S), None when it cannot say.
    """

    offsets: Mapping[str, Mapping[str, float]]
    g92: Mapping[str, float] = field(default_factory=dict)
    speed: float | None = None


@dataclass(frozen=True, slots=True)
class ResumePlan:
    line: int  # the file line the job resumes at
    state: ModalState  # the modal state in force before that line
    preamble: list[str]  # what restores the state (spindle, coolant not yet on)
    approach: list[str]  # up, across, spindle on, dwell, down
    position: dict[str, float | None]  # the work position the line starts from (file units)
    uncertain: list[str]
    machine: dict[str, float | None] = field(default_factory=dict)  # the same point, machine mm
    plunge_feed: float | None = None  # mm/min, how the approach goes down

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
            "machine_position": self.machine,
            "plunge_feed": self.plunge_feed,
            "units": s.units,
            "wcs": s.wcs,
            "feed": s.feed,
            "spindle": s.spindle,
            "speed": s.speed,
            "tool": s.tool,
            "coolant": {"mist": s.mist, "flood": s.flood},
            "uncertain": self.uncertain,
        }


@dataclass(slots=True)
class _Read:
    """A model reading the file, and the highest machine Z its moves reached."""

    model: GcodeModel
    top: float = -math.inf  # mm, machine coordinates
    top_line: int = 0
    # The first line whose Z the machine's tool table offset (G43) moved by an amount
    # hostd cannot read: from there the file's highest machine Z is not known.
    table_offset_line: int | None = None

    def step(self, text: str) -> None:
        self.model.step(text)
        # Where the machine's Z went: the programmed point plus the tool length offset
        # (G43.1's; under G43 the machine's table holds it, not known: the point alone).
        tlo = self.model.tlo
        point = self.model.pos[2]
        if math.isnan(tlo) and self.table_offset_line is None and not math.isnan(point):
            self.table_offset_line = self.model.line
        z = point + (0.0 if math.isnan(tlo) else tlo)
        if z > self.top:  # NaN (not known) never is
            self.top, self.top_line = z, self.model.line


def state_before(lines: Iterable[str], line: int, dialect: Dialect, board: Board) -> _Read:
    """The model after reading lines 1 .. line - 1 (streamed, O(1) memory), from `board`,
    with the highest the file took the tool meanwhile.

    Which G92 the file started with: none, when the file sets its own before the line
    (the board's may be what the lost job itself set: taken as the start, it would
    shift everything read before the file's G92); else the board's (an operator's,
    set before the job, which the job ran with).
    """
    own = _Read(GcodeModel(dialect, offsets=board.offsets, keep_offsets=True))
    held = None
    if any(board.g92.values()):
        held = _Read(GcodeModel(dialect, offsets=board.offsets, g92=board.g92, keep_offsets=True))
    for number, text in enumerate(lines, start=1):
        if number >= line:
            break
        own.step(text)
        if held is not None:
            held.step(text)
    return own if held is None or own.model.g92_line is not None else held


def plan_resume(
    lines: Iterable[str],
    line: int,
    dialect: Dialect,
    *,
    board: Board | None,
    safe_z: float | None,
    dwell: float = DEFAULT_DWELL,
    plunge_feed: float | None = None,
    laser: bool = False,
) -> ResumePlan:
    """The plan to resume at `line` on a board holding `board`.

    `safe_z`: the safe height in machine coordinates (mm); `plunge_feed` (mm/min):
    the configured one, None for the file's own only; `laser`: the tool is a laser
    (no dwell, the beam on only in position).
    """
    if board is None:
        raise ResumeError(
            "the board's coordinate offsets are not known (is the machine connected?): "
            "without them the approach cannot be planned in machine coordinates"
        )
    read = state_before(lines, line, dialect, board)
    model = read.model
    state = model.state()
    uncertain: list[str] = []
    if model.line < line - 1:
        raise ResumeError(f"the file has {model.line} lines: there is no line {line}")
    if state.ended:
        uncertain.append("the program ended (M2/M30) before this line")
    uncertain += state.unrestorable()
    uncertain += [f"{text} (first at line {first})" for text, (first, _) in model.warnings.items()]
    uncertain += _offsets_written(state, board)
    g92_held = {a: v for a, v in board.g92.items() if v}
    if g92_held:
        held = " ".join(f"{a.upper()}{_num(v, 3)}" for a, v in g92_held.items())
        if model.g92_line is None:
            uncertain.append(
                f"the board holds a G92 offset ({held} mm) that the file does not set "
                "before this line: the plan takes it as the one the job ran with"
            )
        else:
            uncertain.append(
                f"the board's G92 offset ({held} mm) is replaced by the file's (line "
                f"{model.g92_line})"
            )
    off = dataclasses.replace(state, spindle="M5", mist=False, flood=False)
    preamble = [_supported(text, dialect) for text in off.preamble("M6" not in dialect.unsupported)]
    preamble = [text for text in preamble if text]
    if safe_z is None:
        raise ResumeError(
            "no safe height: set the machine's safe_z, or home it so that the top of "
            "its Z travel is known"
        )
    target = _target(state, line)
    scale = state.scale
    places = 6 if state.units == "G20" else 4  # a micron either way
    approach: list[str] = []
    # The board's G92 must be the file's when its lines run again: cleared here, set at
    # the resume point (G92 reads the position it stands at).
    board_g92 = [float(board.g92.get(a, 0.0)) for a in AXES]
    file_g92 = [float(state.g92.get(a) or 0.0) for a in AXES]
    reset_g92 = any(abs(b - f) > 1e-9 for b, f in zip(board_g92, file_g92, strict=True))
    if reset_g92:
        approach.append("G92.1")
    # Never across lower than the file itself went before the line: a safe height set
    # below its clearance (the work's top, a clamp) would drag the tool through them.
    climb = safe_z
    if read.top > safe_z + 1e-9:
        climb = read.top
        uncertain.append(
            f"the file went up to Z{_num(read.top, 3)} mm (machine, line {read.top_line}), "
            f"above the safe height Z{_num(safe_z, 3)}: the approach crosses at that height"
        )
    if read.table_offset_line is not None:
        uncertain.append(
            f"the file ran under G43 from line {read.table_offset_line}: its heights moved by "
            "the tool table's length offset, which hostd cannot read, so its clearance in "
            f"machine Z is not known; the approach crosses at Z{_num(climb, 3)} mm (machine): "
            "check that it clears the work and the clamps with this tool"
        )
    approach.append(f"G90 G53 G0 Z{_num(climb / scale, places)}")
    x, y = (_num(target[a] / scale, places) for a in ("x", "y"))
    approach.append(f"G53 G0 X{x} Y{y}")
    on = _switch_on(state, board, uncertain)
    if state.mist:
        approach.append("M7")
    if state.flood:
        approach.append("M8")
    if on and not laser:
        approach.append(on)
        if dwell > 0:
            approach.append(f"G4 P{_num(dwell, 3)}")
    feed = _plunge(state, plunge_feed, line, uncertain)
    modes = "G94 " if state.feed_mode != "G94" else ""
    if state.tlo is not None:
        z = target["z"] + state.tlo
        approach.append(f"{modes}G53 G1 Z{_num(z / scale, places)} F{_num(feed / scale, 3)}")
    else:
        # G43: the offset is in the machine's tool table. The file's own frame, in which
        # the board adds it (without G92 if it was cleared above).
        wz = target["z"] - float(board.offsets.get(state.wcs, {}).get("z", 0.0))
        if not reset_g92:
            wz -= file_g92[2]
        approach.append(f"{modes}G1 Z{_num(wz / scale, places)} F{_num(feed / scale, 3)}")
        uncertain.append(
            f"G43 H{state.tool_h}: the tool goes down in the file's coordinates, by the "
            "board's tool length offset, as the file's own lines do"
        )
    if on and laser:
        approach.append(on)
    if reset_g92:
        words = [
            f"{a.upper()}{_num(float(state.work.get(a) or 0.0), places)}"
            for a, v in zip(AXES, file_g92, strict=True)
            if v and state.work.get(a) is not None
        ]
        if words:
            approach.append(f"G92 {' '.join(words)}")
            uncertain.append(
                "the G92 offset is set again from the file's positions (G92.1, then G92)"
            )
    if state.feed_mode != "G94":
        approach.append(state.feed_mode)
    elif state.feed is not None:
        approach.append(f"F{_num(state.feed, 3)}")  # the file's feed, not the plunge's
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
    position = {a: state.work.get(a) for a in LINEAR}
    tlo = state.tlo if state.tlo is not None else math.nan
    machine: dict[str, float | None] = {
        a: _finite(target[a] + (tlo if a == "z" else 0.0)) for a in LINEAR
    }
    return ResumePlan(line, state, preamble, approach, position, uncertain, machine, feed)


def _finite(value: float) -> float | None:
    return None if math.isnan(value) else value


def _target(state: ModalState, line: int) -> dict[str, float]:
    """The programmed point the resume line starts from, in machine coordinates (mm)."""
    target = {a: state.machine.get(a) for a in LINEAR}
    missing = [a.upper() for a, v in target.items() if v is None]
    if missing:
        why = "no absolute move sets it before that line"
        if state.tool_length == "G43" and "Z" in missing:
            why += ", or G53 moved it under a tool length offset from the machine's table"
        raise ResumeError(
            f"the position at line {line} is not known from the file ({', '.join(missing)}: "
            f"{why}); resume at a later line, or with restore false and the machine placed "
            "by hand"
        )
    return {a: float(v) for a, v in target.items() if v is not None}


def _offsets_written(state: ModalState, board: Board) -> list[str]:
    """What the file wrote with G10 before the line: the board keeps its own, say which."""
    out = []
    for wcs, axes in state.wcs_set.items():
        wrote = (state.wcs_file or {}).get(wcs, {})
        held = board.offsets.get(wcs)
        if held is None:
            raise ResumeError(
                f"the file sets {wcs} with G10 and the board has no {wcs}: it cannot resume"
            )
        parts = []
        for a in axes:
            w, h = wrote.get(a), held.get(a)
            now = "?" if h is None else _num(h, 3)
            if w is None:
                parts.append(f"{a.upper()} {now} (the file's value is not known)")
            elif h is None or not math.isclose(w, h, abs_tol=1e-3):
                parts.append(f"{a.upper()} {now} where the file wrote {_num(w, 3)}")
            else:
                parts.append(f"{a.upper()} {now}, as the file wrote")
        out.append(
            f"the file sets {wcs} with G10 (last at line {state.g10_line}); the preamble "
            f"does not write it, and the plan uses the board's {wcs}: {'; '.join(parts)} "
            "(mm). Check that it is the offset the job ran with before resuming"
        )
    return out


def _switch_on(state: ModalState, board: Board, uncertain: list[str]) -> str | None:
    """The spindle or laser line, with the speed in force; never S0 for a missing S."""
    if state.spindle == "M5":
        return None
    if state.speed is not None:
        return f"S{_num(state.speed, 3)} {state.spindle}"
    if board.speed is not None and board.speed <= 0:
        raise ResumeError(
            f"the file turns the spindle on ({state.spindle}) without a speed, and the "
            "board's is 0 now: set the speed on the board (S...) and plan again, or "
            "resume at a line after the file's own S"
        )
    held = "unknown" if board.speed is None else f"S{_num(board.speed, 3)}"
    uncertain.append(
        f"the file never set a speed before this line: {state.spindle} goes without S, "
        f"at the board's own speed ({held})"
    )
    return state.spindle


def _plunge(state: ModalState, configured: float | None, line: int, uncertain: list[str]) -> float:
    """The feed (mm/min) to go down at: the file's plunge feed or the configured one,
    whichever is slower; the cutting feed only where neither is known."""
    known = [f for f in (state.plunge_feed, configured) if f is not None and f > 0]
    if known:
        return min(known)
    cutting = state.feed * state.scale if state.feed and state.feed_mode == "G94" else None
    if cutting is None:
        raise ResumeError(
            f"no feed to go down at before line {line}: the file made no feed move along Z "
            "alone and has no feed in force; set the machine's plunge_feed"
        )
    uncertain.append(
        "the file made no feed move along Z alone before this line and no plunge_feed is "
        f"set: the tool goes down at the cutting feed ({_num(cutting, 1)} mm/min)"
    )
    return cutting


def _supported(text: str, dialect: Dialect) -> str:
    """A preamble line without the words the dialect refuses (grbl: G64, G90.1, M6...)."""
    words = text.split()
    kept = [w for w in words if _code(w) not in dialect.unsupported]
    if kept != words and not any(w[0] in "GMTSF" for w in kept):
        return ""  # only the refused code's own words (G43's H) are left
    return " ".join(kept)


def _code(word: str) -> str:
    letter, number = word[0], word[1:]
    try:
        return f"{letter}{float(number):g}"
    except ValueError:
        return word
