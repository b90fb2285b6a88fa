"""g2core's combined machine state (`stat`), the codes every layer speaks.

Codes and names are g2core's `cmCombinedState` without the `COMBINED_`
prefix; the API publishes them as `{"code": 2, "name": "ALARM"}`.
"""

from __future__ import annotations

from enum import IntEnum


class MachineState(IntEnum):
    INITIALIZING = 0
    READY = 1
    ALARM = 2
    PROGRAM_STOP = 3
    PROGRAM_END = 4
    RUN = 5
    HOLD = 6
    PROBE = 7
    CYCLE = 8
    HOMING = 9
    JOG = 10
    INTERLOCK = 11
    SHUTDOWN = 12
    PANIC = 13

    @property
    def is_lockout(self) -> bool:
        """ALARM, SHUTDOWN and PANIC: the controller drains and rejects actions."""
        return self in LOCKOUTS

    @property
    def is_resting(self) -> bool:
        """Not moving and ready for a new host operation."""
        return self in _RESTING


# The lockout states (`is_lockout`), as a set for the gates that add states of their own.
LOCKOUTS = frozenset({MachineState.ALARM, MachineState.SHUTDOWN, MachineState.PANIC})
_RESTING = frozenset({MachineState.READY, MachineState.PROGRAM_STOP, MachineState.PROGRAM_END})


def state_from_code(code: object) -> MachineState | None:
    """The state for a `stat` value as received, or None when it is not one."""
    if isinstance(code, bool) or not isinstance(code, int | float) or code != int(code):
        return None
    try:
        return MachineState(int(code))
    except ValueError:
        return None
