"""Where the tool is, in time: the block being executed, a hold's deceleration, a halt.

Each move runs at a constant speed (its feed, scaled by the configured speed
factor) from the position the machine stands at when it starts; a feedhold
decelerates linearly to a stop over the configured time (or sooner, at the
end of the move) and leaves the rest of the move to be resumed. g2core plans
jerk-limited S-curves across blocks; a host only sees positions and speeds
in status reports, so constant speed is enough to make them move.

Pure: the time is always passed in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from hostd.sim.config import AXES
from hostd.sim.gcode import Arc, Block, Dwell, Home, Move, Probe


def path_length(start: dict[str, float], move: Move) -> float:
    if move.arc is None:
        return math.sqrt(sum((move.target[a] - start[a]) ** 2 for a in AXES))
    arc = move.arc
    linear = [a for a in AXES if a not in arc.axes]
    rise = math.sqrt(sum((move.target[a] - start[a]) ** 2 for a in linear))
    return math.hypot(abs(arc.sweep) * arc.radius, rise)


def point_on(start: dict[str, float], move: Move, fraction: float) -> dict[str, float]:
    """The point `fraction` (0..1) of the way along `move` from `start`."""
    f = min(max(fraction, 0.0), 1.0)
    if f >= 1.0:
        return dict(move.target)
    point = {a: start[a] + (move.target[a] - start[a]) * f for a in AXES}
    arc = move.arc
    if arc is not None:
        angle = arc.start_angle + arc.sweep * f
        point[arc.axes[0]] = arc.center[0] + arc.radius * math.cos(angle)
        point[arc.axes[1]] = arc.center[1] + arc.radius * math.sin(angle)
    return point


def remainder(move: Move, fraction: float) -> Move:
    """The part of `move` still to run after `fraction` of it is done."""
    arc = move.arc
    if arc is None:
        return move
    done = arc.sweep * fraction
    rest = Arc(arc.axes, arc.center, arc.radius, arc.start_angle + done, arc.sweep - done)
    return replace(move, arc=rest)


@dataclass(frozen=True, slots=True)
class Traversed:
    """A move the machine made, from `start` (machine mm): what a test checks the tool's
    path against. `laser`: the board was in laser mode, where the beam is off in G0."""

    start: dict[str, float]
    move: Move
    laser: bool = False

    @property
    def cutting(self) -> bool:
        """The spindle runs or the beam burns while it moves."""
        if self.move.spindle == "M5" or self.move.speed <= 0:
            return False
        return not (self.laser and self.move.rapid)

    def points(self, step: float) -> list[dict[str, float]]:
        """Points along the path, at most `step` mm apart, both ends included."""
        count = max(1, math.ceil(path_length(self.start, self.move) / step))
        return [point_on(self.start, self.move, i / count) for i in range(count + 1)]


@dataclass
class Active:
    """The block being executed, started at `t0` from `start`.

    For a move `rate` is the path speed in mm per real second; a dwell has no
    path and just lasts `duration`.
    """

    block: Block
    start: dict[str, float]
    t0: float
    duration: float
    length: float = 0.0
    feed: float = 0.0  # mm/min, what the status report calls vel
    move: Move | None = None  # the path (a homing cycle runs as a rapid move)
    # Set while a feedhold decelerates: from distance s0 at time d0, over dt seconds.
    d0: float | None = None
    s0: float = 0.0
    dt: float = 0.0

    @property
    def rate(self) -> float:
        return self.length / self.duration if self.duration > 0 else 0.0

    @property
    def decelerating(self) -> bool:
        return self.d0 is not None

    @property
    def end(self) -> float:
        """When this block is done, or (while decelerating) when the tool stands still."""
        if self.d0 is not None:
            return self.d0 + self.dt
        return self.t0 + self.duration

    def distance(self, now: float) -> float:
        if self.d0 is not None:
            tau = min(max(now - self.d0, 0.0), self.dt)
            rate = self.rate
            return self.s0 + rate * tau - rate * tau * tau / (2 * self.dt) if self.dt else self.s0
        if self.duration <= 0:
            return self.length
        return self.length * min(max((now - self.t0) / self.duration, 0.0), 1.0)

    def fraction(self, now: float) -> float:
        if self.move is None:
            return min(max((now - self.t0) / self.duration, 0.0), 1.0) if self.duration else 1.0
        return self.distance(now) / self.length if self.length else 1.0

    def position(self, now: float) -> dict[str, float]:
        if self.move is None:
            return dict(self.start)
        return point_on(self.start, self.move, self.fraction(now))

    def velocity(self, now: float) -> float:
        """mm/min along the path: the feed, falling to zero over a hold's deceleration."""
        if self.move is None or self.length == 0 or now >= self.end:
            return 0.0
        if self.d0 is not None:
            return self.feed * max(0.0, 1.0 - (now - self.d0) / self.dt) if self.dt else 0.0
        return self.feed

    def begin_hold(self, now: float, decel: float) -> None:
        """Start decelerating; it stops after `decel` s, or at the end of the move."""
        s = self.distance(now)
        rate = self.rate
        remaining = self.length - s
        dt = decel
        if self.move is None or rate == 0:
            dt = 0.0
        elif rate * decel / 2 > remaining:
            dt = 2 * remaining / rate
        self.d0, self.s0, self.dt = now, s, dt

    def rest(self, now: float) -> Block | None:
        """What is left of the block at `now`, as a block to run later (None if done)."""
        block = self.block
        if isinstance(block, Dwell):
            left = block.seconds - max(now - self.t0, 0.0)
            return Dwell(left, block.n) if left > 1e-9 else None
        if self.move is None:
            return None
        fraction = self.fraction(now)
        if fraction >= 1.0 - 1e-12:
            return None
        if isinstance(block, Home | Probe):
            return block  # homing is started over; a straight probe runs on to its target
        return remainder(self.move, fraction)


def start_block(
    block: Block,
    position: dict[str, float],
    now: float,
    *,
    speed_factor: float,
    rapid_rate: float,
    instant: bool,
) -> Active:
    """Begin executing `block` with the tool at `position`."""
    if isinstance(block, Dwell):
        duration = 0.0 if instant else block.seconds / speed_factor
        return Active(block, dict(position), now, duration)
    if isinstance(block, Home):
        target = dict(position)
        for a in block.axes:
            target[a] = 0.0
        move = Move(target, rapid_rate, block.n, rapid=True)
    elif isinstance(block, Move):
        move = block
    elif isinstance(block, Probe):
        move = block.move
    else:
        return Active(block, dict(position), now, 0.0)
    feed = rapid_rate if move.rapid else move.feed
    length = path_length(position, move)
    duration = 0.0
    if not instant and feed > 0:
        duration = length / (feed / 60.0) / speed_factor
    return Active(block, dict(position), now, duration, length, feed, move)
