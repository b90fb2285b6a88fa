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
from hostd.sim.gcode import Probe

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
    surface: tuple[str, float] | None, start: Mapping[str, float], block: Probe
) -> dict[str, float] | None:
    """Where on its way the probe input changes to the tripped state, if it does."""
    if surface is None:
        return None
    axis, at = surface
    end = block.move.target
    if not block.on_contact:
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
