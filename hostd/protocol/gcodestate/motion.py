"""Where a move ends: linear moves, arcs, and the moves the file cannot place.

The layer of `GcodeModel` (model.py) above the figures (figures.py): a move
puts its end point, in machine coordinates, from the program's words and the
modes in force (distance mode, units, coordinate system, G92, the tool
length offset), counts itself, finds an arc's centre and checks that the arc
closes as the dialect would accept, then hands the move to the figures.
"""

from __future__ import annotations

import math

from hostd.protocol.gcodestate.figures import Figures, _arc_length
from hostd.protocol.gcodestate.modes import _LINEAR, NAN

# Plane -> (first axis, second axis, helix axis, the two offset letters), LinuxCNC's order.
_PLANES = {"G17": (0, 1, 2, "I", "J"), "G18": (2, 0, 1, "K", "I"), "G19": (1, 2, 0, "J", "K")}


class Motion(Figures):
    """A block's move, once blocks.py has decided there is one."""

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

    def _unknown_end(self, motion: str, axes: dict[int, float]) -> None:
        if motion.startswith("G38"):
            self.warn(f"{motion} probing: the position afterwards is where the probe stopped")
            for i in axes:
                self.pos[i] = NAN
        else:
            self.warn(f"{motion} canned cycles are not modelled: Z is unknown afterwards")
            self.pos[2] = NAN

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
