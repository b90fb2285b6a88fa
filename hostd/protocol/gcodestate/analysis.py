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
    seconds: float = 0.0  # the estimated duration: moves at their feeds, dwells
    # The file line where each axis's bound was reached: (low, high), for travel errors.
    bound_lines: dict[str, tuple[int, int]] | None = None

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
    velocity: Mapping[str, float] | None = None,
    acceleration: Mapping[str, float] | None = None,
) -> Analysis:
    """Read a whole program (streamed) and return its figures.

    `velocity` (mm/min) and `acceleration` (mm/s^2) per axis, from the machine's
    settings when known, shape the estimate.
    """
    model = GcodeModel(
        dialect,
        start=start if start is not None else dict.fromkeys(AXES, 0.0),
        offsets=offsets if offsets is not None else {"G54": dict.fromkeys(AXES, 0.0)},
        homes=homes,
        track_bounds=True,
        velocity=velocity,
        acceleration=acceleration,
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
        seconds=model.seconds,
        bound_lines={AXES[i]: (model.low_at[i], model.high_at[i]) for i in sorted(model.moved)},
    )


def beyond_travel(
    bounds: Bounds,
    offset: Mapping[str, float],
    travel: Mapping[str, tuple[float, float]],
    lines: Mapping[str, tuple[int, int]] | None = None,
) -> list[str]:
    """The axes whose moves leave the machine's travel: program bounds (mm) moved by the
    work offset in force (machine minus work position, mm), against travel (mm).
    `lines`: where each bound was reached (Analysis.bound_lines), named in the text."""
    out = []
    for axis, (low, high) in bounds.items():
        if axis not in travel or axis not in offset:
            continue
        t_low, t_high = travel[axis]
        m_low, m_high = low + offset[axis], high + offset[axis]
        if m_low < t_low - 1e-6 or m_high > t_high + 1e-6:
            where = ""
            if lines and axis in lines:
                at = [
                    f"line {n}"
                    for n, out_of in zip(
                        lines[axis], (m_low < t_low - 1e-6, m_high > t_high + 1e-6), strict=True
                    )
                    if out_of and n
                ]
                where = f" (at {', '.join(at)})" if at else ""
            out.append(
                f"{axis.upper()} runs from {m_low:.3f} to {m_high:.3f} mm (machine), "
                f"outside the travel {t_low:.3f} to {t_high:.3f} mm{where}"
            )
    return out
