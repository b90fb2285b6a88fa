"""G38.2-G38.5 probing (cycle_probing.cpp): the cycle's record and the probe input.

The cycle itself runs on the board's state (`_probe_start`, `_probe_finish` and
the rest, beside the planner that starts it); what needs none of that state is
here: whether the probe input is closed where the tool stands, and where on a
move it trips.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from hostd.sim.config import AXES, EPS

SENSOR_REACH = 1.0  # mm: a probe this close to the tool sensor's X and Y is over it

MINIMUM_PROBE_TRAVEL = 0.254  # mm, cycle_probing.cpp
PROBE_AXES = ("x", "y", "z", "a", "b", "c")  # the axes `_send_probe_report` prints


@dataclass
class ProbeCycle:
    """A G38.x cycle under way: whether its input tripped, whether failing is an alarm."""

    alarm: bool
    tripped: bool = False


def probe_touching(surface: tuple[str, float] | None, at: Mapping[str, float]) -> bool:
    """The probe input: closed while the tool touches the surface (`probe_surface`)."""
    return surface is not None and abs(at[surface[0]] - surface[1]) < EPS


def probe_trip(
    surface: tuple[str, float] | None,
    start: Mapping[str, float],
    end: Mapping[str, float],
    *,
    on_contact: bool,
) -> dict[str, float] | None:
    """Where on its way to `end` the probe input changes to the tripped state, if it does."""
    if surface is None:
        return None
    axis, at = surface
    if not on_contact:
        return dict(start)  # touching at the start: it trips as the tool leaves
    if start[axis] == end[axis]:
        return None
    fraction = (at - start[axis]) / (end[axis] - start[axis])
    if not 0.0 <= fraction <= 1.0:
        return None
    point = {a: start[a] + (end[a] - start[a]) * fraction for a in AXES}
    point[axis] = at
    return point


@dataclass(frozen=True, slots=True)
class ToolSensor:
    """A fixed tool-length sensor (issue 29): where it is, in machine mm, and the machine
    Z at which a tool of length 0 closes it. A tool `length` mm longer closes it that
    much higher: its tip reaches the sensor sooner."""

    x: float
    y: float
    z: float


def sensor_surface(
    sensor: ToolSensor | None, tool_length: float, at: Mapping[str, float]
) -> tuple[str, float] | None:
    """The sensor as a Z surface for the tool in the spindle, when `at` is over it."""
    if sensor is None:
        return None
    if abs(at["x"] - sensor.x) > SENSOR_REACH or abs(at["y"] - sensor.y) > SENSOR_REACH:
        return None
    return "z", sensor.z + tool_length


@dataclass(frozen=True)
class TouchPlate:
    """A conductive touch plate on the work, wired to the probe input; the bit is the other pole.

    `top` is the machine Z of its top face. Without walls it is a Z plate: it
    lies flat on the work, wider than any move that probes it. A corner plate
    (`x_face`, `y_face` given) also has walls: it covers x >= x_face and
    y >= y_face, so a bit moving +X beside it meets the wall at x_face, and +Y
    at y_face. The bit is a cylinder of `tool_radius` with its tip at the
    reported position: it meets a wall `tool_radius` before its centre does
    (a square end, exact for the axis-aligned moves a corner probe makes).
    Every point of the solid counts as touching: a bit pressed into it stays
    in contact.
    """

    top: float
    x_face: float | None = None
    y_face: float | None = None
    tool_radius: float = 0.0

    def _bounds(self) -> list[tuple[str, float, int]]:
        """Half-spaces (axis, bound, sign): inside when sign * (p - bound) >= 0."""
        out = [("z", self.top, -1)]
        if self.x_face is not None:
            out.append(("x", self.x_face - self.tool_radius, 1))
        if self.y_face is not None:
            out.append(("y", self.y_face - self.tool_radius, 1))
        return out

    def touching(self, at: Mapping[str, float]) -> bool:
        return all(sign * (at[axis] - bound) >= -EPS for axis, bound, sign in self._bounds())

    def entry(self, start: Mapping[str, float], end: Mapping[str, float]) -> float | None:
        """Where along start -> end (0..1) the bit first touches the plate, if it does."""
        low, high = 0.0, 1.0
        for axis, bound, sign in self._bounds():
            s = sign * (start[axis] - bound)
            e = sign * (end[axis] - bound)
            if s >= -EPS and e >= -EPS:
                continue  # inside this half-space the whole way
            if s < -EPS and e < -EPS:
                return None  # never inside it
            t = s / (s - e)  # where it crosses the bound
            if s < -EPS:
                low = max(low, t)
            else:
                high = min(high, t)
        return low if low <= high + EPS else None


def probe_input(
    surface: tuple[str, float] | None, plate: TouchPlate | None, at: Mapping[str, float]
) -> bool:
    """Whether the probe input is closed with the tool at `at`: on the surface or the plate."""
    return probe_touching(surface, at) or (plate is not None and plate.touching(at))


def contact(
    surface: tuple[str, float] | None,
    plate: TouchPlate | None,
    start: Mapping[str, float],
    block_target: Mapping[str, float],
    on_contact: bool,
) -> dict[str, float] | None:
    """Where a probe move from `start` toward `block_target` trips, if it does: the
    nearer of the surface and the plate. A move seeking loss of contact (G38.4/5)
    trips as it starts, where either touches."""
    if not on_contact:
        return dict(start) if probe_input(surface, plate, start) else None
    points: list[tuple[float, dict[str, float]]] = []
    hit = probe_trip(surface, start, block_target, on_contact=True)
    if hit is not None:
        axis = surface[0] if surface is not None else "z"
        span = block_target[axis] - start[axis]
        points.append(((hit[axis] - start[axis]) / span if span else 0.0, hit))
    if plate is not None:
        t = plate.entry(start, block_target)
        if t is not None:
            point = {a: start[a] + (block_target[a] - start[a]) * t for a in start}
            points.append((t, point))
    return min(points, key=lambda p: p[0])[1] if points else None
