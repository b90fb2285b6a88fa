"""A program's figures, gathered by the modal model in the same pass (file.analyze).

Bounds are of the programmed point in machine coordinates (mm), with the
coordinate-system offsets the caller gives (none: zero, so the bounds are the
program's own, relative to its work origin) and the start at that origin
unless told otherwise. Arcs count with their extreme points, not only their
ends. A move whose position is unknown (after G28 with an unknown home, a
probe, a tool length offset change) adds nothing until an absolute move
makes it known again.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from hostd.protocol.gcodestate.dialects import G2CORE, Dialect
from hostd.protocol.gcodestate.model import GcodeModel
from hostd.protocol.gcodestate.state import AXES, LINEAR, MM_PER_INCH, ModalState

Bounds = dict[str, tuple[float, float]]


@dataclass(frozen=True, slots=True)
class GcodeWarning:
    text: str
    line: int  # the first line it concerns
    count: int


@dataclass(frozen=True, slots=True)
class Analysis:
    lines: int
    blocks: int  # lines with G-code on them
    rapids: int
    feeds: int  # feed moves, arcs included
    arcs: int
    bounds: Bounds  # mm, per axis named in a move (degrees for A B C)
    units: tuple[str, ...]  # G20 / G21 as the file selects them, in order of name
    tools: tuple[int, ...]
    max_speed: float | None
    warnings: tuple[GcodeWarning, ...]
    final: ModalState

    @property
    def file_units(self) -> str | None:
        """The one unit the file uses, None if it selects none or both."""
        return self.units[0] if len(self.units) == 1 else None

    def bounds_in(self, units: str) -> Bounds:
        """The bounds in G20 (inch) or G21 (mm); rotary axes stay in degrees."""
        if units == "G21":
            return dict(self.bounds)
        return {
            a: (lo / MM_PER_INCH, hi / MM_PER_INCH) if a in LINEAR else (lo, hi)
            for a, (lo, hi) in self.bounds.items()
        }


def analyze(
    lines: Iterable[str],
    dialect: Dialect = G2CORE,
    *,
    start: Mapping[str, float] | None = None,
    offsets: Mapping[str, Mapping[str, float]] | None = None,
    homes: Mapping[str, Mapping[str, float]] | None = None,
) -> Analysis:
    """Read a whole program (streamed) and return its figures."""
    model = GcodeModel(
        dialect,
        start=start if start is not None else dict.fromkeys(AXES, 0.0),
        offsets=offsets if offsets is not None else {"G54": dict.fromkeys(AXES, 0.0)},
        homes=homes,
        track_bounds=True,
    )
    model.feed_lines(lines)
    return result(model)


def result(model: GcodeModel) -> Analysis:
    """The figures of a model that has read a program with `track_bounds`."""
    bounds = {
        AXES[i]: (model.low[i], model.high[i])
        for i in sorted(model.moved)
        if math.isfinite(model.low[i]) and math.isfinite(model.high[i])
    }
    return Analysis(
        lines=model.line,
        blocks=model.blocks,
        rapids=model.rapids,
        feeds=model.feeds,
        arcs=model.arcs,
        bounds=bounds,
        units=tuple(sorted(model.units_seen)),
        tools=tuple(sorted(model.tools)),
        max_speed=model.max_speed,
        warnings=tuple(GcodeWarning(t, line, n) for t, (line, n) in model.warnings.items()),
        final=model.state(),
    )
