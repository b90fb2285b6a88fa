"""grbl's and grblHAL's alarm and error codes, and what each means to the host.

From grblHAL/core alarms.h and alarms.c (the alarms, with their
descriptions), errors.h and errors.c (the `error:N` codes). Classic grbl 1.1
(gnea/grbl doc/csv) uses the same numbers for what it has: alarms 1-9 and
errors 1-38; grblHAL adds the rest.
"""

from __future__ import annotations

from hostd.protocol.states import MachineState

ALARMS: dict[int, str] = {
    1: "Hard limit has been triggered. Machine position is likely lost due to sudden halt.",
    2: "Soft limit alarm. G-code motion target exceeds machine travel.",
    3: "Reset/E-stop while in motion. Machine position is likely lost due to sudden halt.",
    4: "Probe fail. Probe is not in the expected initial state before starting probe cycle.",
    5: "Probe fail. Probe did not contact the workpiece within the programmed travel.",
    6: "Homing fail. The active homing cycle was reset.",
    7: "Homing fail. Safety door was opened during homing cycle.",
    8: "Homing fail. Pull off travel failed to clear limit switch.",
    9: "Homing fail. Could not find limit switch within search distances.",
    10: "EStop asserted. Clear and reset",
    11: "Homing required. Execute homing command ($H) to continue.",
    12: "Limit switch engaged. Clear before continuing.",
    13: "Probe protection triggered. Clear before continuing.",
    14: "Spindle at speed timeout. Clear before continuing.",
    15: "Homing fail. Could not find second limit switch for auto squared axis.",
    16: "Power on selftest (POS) failed.",
    17: "Motor fault.",
    18: "Homing fail. Bad configuration.",
    19: "Modbus exception. Timeout or message error.",
    20: "I/O expander communication failed.",
    21: "Non Volatile Storage (EEPROM) failure.",
    22: "Buffer overflow.",
}

# The common state each alarm leaves the board in. An e-stop, a failed self
# test and a motor fault are left only by a reset (grblHAL: "Clear and
# reset"), as g2core's SHUTDOWN is; every other alarm is an ALARM that `$X`
# or `$H` may clear (the board decides: `$X` after a hard limit is refused
# with error 79 on grblHAL, alarms.c `alarm_is_critical`).
ALARM_STATE: dict[int, MachineState] = dict.fromkeys(ALARMS, MachineState.ALARM) | {
    10: MachineState.SHUTDOWN,
    16: MachineState.SHUTDOWN,
    17: MachineState.SHUTDOWN,
}
# Alarms the board leaves only through a reset: until then classic grbl reads
# no line at all, grblHAL refuses `$X` with error 79 (grbl 1.1 protocol.c,
# "Reset to continue"; grblHAL alarms.c `alarm_is_critical`).
CRITICAL = frozenset({1, 2, 10, 17, 20})
# Alarms after which the machine position is no longer known.
POSITION_LOST = frozenset({1, 3, 6, 7, 8, 9, 10, 15, 18})
# error:8: a `$` command refused because the board is not at rest (STATUS_IDLE_ERROR).
IDLE_ERROR = 8

ERRORS: dict[int, str] = {
    1: "G-code words consist of a letter and a value. Letter was not found.",
    2: "Missing the expected G-code word value or numeric value format is not valid.",
    3: "'$' system command was not recognized or supported.",
    4: "Negative value received for an expected positive value.",
    5: "Homing cycle failure. Homing is not configured via settings.",
    6: "Step pulse time must be greater or equal to 2 microseconds.",
    7: "A settings read failed. Auto-restoring affected settings to default values.",
    8: "'$' command cannot be used unless controller state is IDLE.",
    9: "G-code commands are locked out during alarm or jog state.",
    10: "Soft limits cannot be enabled without homing also enabled.",
    11: "Max characters per line exceeded. Received command line was not executed.",
    12: "'$' setting value cause the step rate to exceed the maximum supported.",
    13: "Safety door detected as opened and door state initiated.",
    14: "Build info or startup line exceeded line length limit. Line not stored.",
    15: "Jog target exceeds machine travel. Jog command has been ignored.",
    16: "Jog command has no '=' or contains prohibited g-code.",
    17: "Laser mode requires PWM output.",
    18: "Reset asserted",
    19: "Non positive value",
    20: "Unsupported or invalid g-code command found in block.",
    21: "More than one g-code command from same modal group found in block.",
    22: "Feed rate has not yet been set or is undefined.",
    23: "G-code command in block requires an integer value.",
    24: "More than one g-code command that requires axis words found in block.",
    25: "Repeated g-code word found in block.",
    26: "No axis words found in block for g-code command or current modal state "
    "which requires them.",
    27: "Line number value is invalid.",
    28: "G-code command is missing a required value word.",
    29: "G59.x work coordinate systems are not supported.",
    30: "G53 only allowed with G0 and G1 motion modes.",
    31: "Axis words found in block when no command or current modal state uses them.",
    32: "G2 and G3 arcs require at least one in-plane axis word.",
    33: "Motion command target is invalid.",
    34: "Arc radius value is invalid.",
    35: "G2 and G3 arcs require at least one in-plane offset word.",
    36: "Unused value words found in block.",
    37: "G43.1 dynamic tool length offset is not assigned to configured tool length axis.",
    38: "Tool number greater than max supported value or undefined tool selected.",
    39: "Value out of range.",
    40: "G-code command not allowed when tool change is pending.",
    41: "Spindle not running when motion commanded in CSS or spindle sync mode.",
    42: "Plane must be ZX for threading.",
    43: "Max. feed rate exceeded.",
    44: "RPM out of range.",
    45: "Only homing is allowed when a limit switch is engaged.",
    46: "Home machine to continue.",
    47: "ATC: current tool is not set. Set current tool with M61.",
    48: "Value word conflict.",
    49: "Power on self test failed. A hard reset is required.",
    50: "Emergency stop active.",
    51: "Motor fault.",
    52: "Setting value is out of range.",
    53: "Setting is not available, possibly due to limited driver support.",
    54: "Retract position is less than drill depth.",
    55: "Attempt to home two auto squared axes at the same time.",
    56: "Coordinate system is locked.",
    57: "Unexpected file demarcation.",
    58: "Port is not available",
    79: "Not allowed while critical event is active.",
}
# Errors that say the board refused a line because of its lockout, not the line:
# the job's end then carries the lockout's API code, as g2core's 204 does.
LOCKOUT_ERRORS = frozenset({9, 45, 46, 49, 50, 79})


def alarm_text(code: int) -> str:
    return ALARMS.get(code, f"alarm {code}")


def error_text(code: int) -> str:
    return ERRORS.get(code, f"error {code}")
