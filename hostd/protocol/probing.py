"""Probing with a touch plate: the lines of a Z and an XYZ corner probe, and their zeros.

Pure: what to send and what the work position should read, from the plate's
geometry; no waiting, no board. The machine layer (hostd/machine/probing.py)
runs the steps, one answer at a time; a session says the dialect's part (how
the probe input is seen, the `G10 L20 P` word).

Geometry (docs/operations.md, "Probing"): a Z plate lies on the work, its
top `plate` mm above it. The corner plate is the same plate with two walls,
of the same thickness, hanging down along the work's X-min and Y-min edges
(the front left corner). Work zero is the work's corner: X0 at its left
edge, Y0 at its front edge, Z0 on its top. The bit touches the top with its
tip and the walls with its side, so X and Y are off by its radius as well.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

# How far an XYZ probe moves the bit off the plate before it goes down beside it,
# as a fraction of max_travel: the bit must start over the plate within this of
# each wall (less its radius).
CLEARANCE: Final = 0.5


@dataclass(frozen=True)
class ProbeInput:
    """How the host sees the probe input.

    `key`: the field that holds it (1/true closed), None where the board cannot
    show it. `query`: the line whose answer holds it; None when every status
    report holds it (grbl's `Pn:P`).
    """

    key: str | None
    query: str | None = None


def number(value: float) -> str:
    text = f"{value:.4f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text


def probe_line(axis: str, target: float, feed: float, *, must_touch: bool = True) -> str:
    """G38.2 (an alarm when it misses: the board's own stop) or G38.3 (no alarm)."""
    code = "G38.2" if must_touch else "G38.3"
    return f"{code} {axis.upper()}{number(target)} F{number(feed)}"


def touch_value(axis: str, plate: float, tool_diameter: float) -> float:
    """What the work position of `axis` reads with the bit touching the plate."""
    if axis == "z":
        return plate  # the tip on the plate's top: the work's top is `plate` below
    # The side of the bit on the wall's outer face: the work's edge is a wall and a
    # radius further on.
    return -(plate + tool_diameter / 2)
