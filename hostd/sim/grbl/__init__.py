"""A simulated grbl 1.1h / grblHAL board on a pseudo-terminal, beside the g2core one.

`GrblSimController` (controller.py) plugs a `GrblBoard` (board.py, the pure
firmware model, with system.py, reports.py, realtime.py, lines.py and
motion_control.py) in behind a stable symlink; `GrblConfig` (config.py) picks
the flavour, buffer sizes and settings. Behaviour and its sources are in those modules'
docstrings and docs/simulator.md.
"""

from hostd.sim.grbl.board import GrblBoard
from hostd.sim.grbl.config import GrblConfig
from hostd.sim.grbl.controller import GrblSimController

__all__ = ["GrblBoard", "GrblConfig", "GrblSimController"]
