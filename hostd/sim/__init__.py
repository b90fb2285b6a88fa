"""A simulated g2core controller on pseudo-terminals: the project's test double.

`SimController` plugs a board in behind one or two stable symlinks (like
/dev/serial/by-id links); the host opens them as serial ports. See
controller.py for the API, board.py for the g2core behaviour it follows.
"""

from hostd.sim.config import Received, SimConfig
from hostd.sim.controller import SimController

__all__ = ["Received", "SimConfig", "SimController"]
