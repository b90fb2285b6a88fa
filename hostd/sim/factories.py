"""The simulated boards a daemon plugs in for `data_port = "sim"`, one factory per dialect.

Each dialect's registry entry names its factory by import path
(hostd/protocol/dialects.py, `simulator`), so the daemon builds a board
without importing this package: only a simulated machine loads it.
"""

from __future__ import annotations

from hostd.sim.config import SimConfig
from hostd.sim.controller import SimController
from hostd.sim.grbl.config import GrblConfig
from hostd.sim.grbl.controller import GrblSimController

PLANNER = 48  # g2core's planner buffers (PLANNER_QUEUE_SIZE)


def g2core(data: str, control: str | None, speed: float, history: int) -> SimController:
    """A g2core board, on one port or two."""
    board = SimConfig(speed_factor=speed, planner_depth=PLANNER, history=history)
    return SimController(data, control_path=control, config=board)


def grbl(data: str, control: str | None, speed: float, history: int) -> GrblSimController:
    """grbl 1.1h as most lasers run it, laser mode on ($32=1); it has one port."""
    return GrblSimController(data, GrblConfig(speed_factor=speed, laser_mode=True, history=history))
