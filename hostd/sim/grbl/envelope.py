"""Where a simulated grbl's machine coordinates lie: its work envelope and where homing
leaves each axis, by `$22`, `$23` and `$130`.. (gnea/grbl limits.c; grblHAL core
machine_limits.c `limits_set_work_envelope`, `limits_set_machine_positions`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from hostd.sim.grbl.settings import HOMING_PULLOFF

if TYPE_CHECKING:
    from hostd.sim.grbl.board import GrblBoard


def _origin_at_home(board: GrblBoard) -> bool:
    """grblHAL's `$22` bit 3, "Set machine origin to 0" (settings.h force_set_origin);
    classic grbl's HOMING_FORCE_SET_ORIGIN is a build option, off by default."""
    return board.hal and bool(board._bits(22) & 8)


def _homes_low(board: GrblBoard, i: int) -> bool:
    """`$23` bit i: the axis homes toward its low end."""
    return bool(board._bits(23) & (1 << i))


def envelope(board: GrblBoard, i: int) -> tuple[float, float]:
    """Axis i's machine coordinates: [-max travel, 0] (gnea/grbl limits.c), or with the
    origin set at home on an axis homing low, [0, max travel] (grblHAL machine_limits.c
    limits_set_work_envelope)."""
    travel = board.settings[130 + i]
    if _origin_at_home(board) and _homes_low(board, i):
        return 0.0, travel
    return -travel, 0.0


def home_position(board: GrblBoard, i: int) -> float:
    """Where axis i stands after homing (limits_set_machine_positions): 0 with the origin
    set at home; else pulled off the switch, -pulloff from 0 or from -max travel."""
    if _origin_at_home(board):
        return 0.0
    if _homes_low(board, i):
        return -board.settings[130 + i] + HOMING_PULLOFF
    return -HOMING_PULLOFF
