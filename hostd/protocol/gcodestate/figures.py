"""The figures of each move the analysis needs: the extent it reaches and the time it takes.

The layer of `GcodeModel` (model.py) above its state (modes.py): motion.py
calls these after it has moved the position, and they run only with
`track_bounds` (analysis.py reads the result). They change no modal state,
only the bounds (`low`/`high`, with the line that reached each) and the
estimate (`seconds`), so a reader after the position can skip this file.
"""

from __future__ import annotations

import math

from hostd.protocol.gcodestate.modes import Modes

DEFAULT_RAPID = 5000.0  # mm/min: a rapid's speed when the machine's is not known


class Figures(Modes):
    """Bounds and time of each move, for the analysis (`track_bounds`)."""

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

    def _extend_line(self) -> None:
        low, high = self.low, self.high
        for i, v in enumerate(self.pos):
            if v < low[i]:
                low[i] = v
                self.low_at[i] = self.line
            if v > high[i]:
                high[i] = v
                self.high_at[i] = self.line

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
