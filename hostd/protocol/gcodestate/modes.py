"""The modal state as the model keeps it while it reads, and the snapshot it gives.

`GcodeModel` (model.py) is one class written in layers, a file each; this is
the lowest: every field is declared here, once (the modes, F S T, coolant,
offsets, the position, and the figures the analysis gathers in the same
pass), so a reader of any layer above finds what `self.` holds in one place.
Inside, an unknown value is NaN; `state()` turns it into the frozen
`ModalState` (state.py), where unknown is None. The warnings live here too:
every layer adds to them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

from hostd.protocol.gcodestate.dialects import G2CORE, Dialect
from hostd.protocol.gcodestate.state import AXES, MM_PER_INCH, WCS, ModalState

NAN = math.nan
_LINEAR = 3  # axes below this index are lengths; A B C are degrees, never scaled
# Memory bound: a file of a million lines must not grow the analysis (blocks.py
# holds the others).
MAX_WARNINGS = 100  # distinct warning texts; the rest are counted under one
MORE_WARNINGS = f"more warnings of other kinds: only the first {MAX_WARNINGS} are listed"


class Modes:
    """The controller's modal state, kept while reading a file (see `GcodeModel`).

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

    def warn(self, text: str) -> None:
        seen = self.warnings.get(text)
        if seen is None and len(self.warnings) >= MAX_WARNINGS:
            text = MORE_WARNINGS
            seen = self.warnings.get(text)
        self.warnings[text] = (self.line, 1) if seen is None else (seen[0], seen[1] + 1)

    # --- positions ---------------------------------------------------------------

    def _axis_scale(self, i: int) -> float:
        return self.scale if i < _LINEAR else 1.0

    def _g92_now(self) -> list[float]:
        return list(self.g92) if self.g92_on else [0.0] * 6

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


def _get(values: Mapping[str, float] | None, axis: str) -> float:
    if values is None or axis not in values:
        return NAN
    return float(values[axis])


def _known(value: float) -> float | None:
    return None if math.isnan(value) else value
