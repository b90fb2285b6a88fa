"""The modal state of a G-code program, without I/O: model.py reads, state.py is the result."""

from hostd.protocol.gcodestate.analysis import Analysis, analyze
from hostd.protocol.gcodestate.dialects import DIALECTS, G2CORE, GRBL, LINUXCNC, Dialect
from hostd.protocol.gcodestate.model import GcodeModel
from hostd.protocol.gcodestate.state import ModalState

__all__ = [
    "DIALECTS",
    "G2CORE",
    "GRBL",
    "LINUXCNC",
    "Analysis",
    "Dialect",
    "GcodeModel",
    "ModalState",
    "analyze",
]
