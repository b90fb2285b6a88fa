"""The toy's words: what its board answers and what each means to hostd.

The toy is a line protocol of this test suite's own (README below, in
__init__.py), not any firmware's. Its texts are deliberately unlike g2core's
and grbl's, so a test that reads one of them knows whose table it came from.
"""

from __future__ import annotations

from hostd.protocol.states import MachineState

ERRORS: dict[int, str] = {
    1: "toy: no such word",
    2: "toy: a word without its number",
    3: "toy: the line is too long for the toy",
    9: "toy: locked in an alarm, send UNLOCK",
}
ALARMS: dict[int, str] = {
    1: "toy: the host raised an alarm",
    2: "toy: a limit switch tripped",
}
# The board's state names, onto hostd's shared states.
STATES: dict[str, MachineState] = {
    "IDLE": MachineState.READY,
    "RUN": MachineState.RUN,
    "HOLD": MachineState.HOLD,
    "ALARM": MachineState.ALARM,
}
LOCKED = 9  # the error a line gets in an alarm
MAX_LINE = 80  # bytes, its LF included


def error_text(code: int) -> str:
    return ERRORS.get(code, f"toy error {code}")


def alarm_text(code: int) -> str:
    return ALARMS.get(code, f"toy alarm {code}")
