"""g2core status codes: the number in `f[1]` and `er.st`, its name, and the board's message.

Why a table of our own: the board only sends the number in a footer (the message
text comes only in `er` reports and in text mode), and an operator or a log needs
the words. hostd also decides things by code (a command refused in ALARM,
SHUTDOWN or PANIC, a limit hit), so the codes get names that read like the
firmware's.

Source: synthetos/g2 `g2core/error.h` as of the `edge-preview` branch (fb 101.x,
see ../shared/spec/g2core.md section 3). Names are the `STAT_` names without the
prefix; messages are the `stat_NNN` strings, verbatim, including the few that
are only the number (19, 120, 209, 245), because that is what the board itself
prints for them.

Not in the table:
- The unused placeholders (`STAT_ERROR_NN`, whose message is just the number).
  They are not codes the firmware emits, so `message()` calls them unknown.
  The one exception is 37: its placeholder name has a real message
  ("Backplan hit running buffer"), so it is kept, as `ERROR_37`.
- TinyG (fb >= 400): its status codes differ (e.g. 203 is MACHINE_ALARMED and
  204 LIMIT_SWITCH_HIT there) and are deliberately not here; hostd refuses
  TinyG rather than misread its codes with this table.

Older g2core sources differ in places: 153/155 (arc errors were renumbered),
252/254 (probe errors renamed), 86/87 and 117-120 and 210 (added later). This
table follows fb 101.x.

Pure data and lookups: no I/O, no asyncio.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from enum import IntEnum
from types import MappingProxyType
from typing import Final

__all__ = ["LOCKOUT_RAISED_BY", "MESSAGES", "Status", "StatusInfo", "lookup", "message", "name"]


class Status(IntEnum):
    """Every status code g2core (fb 101.x) defines, named after its `STAT_` constant.

    An IntEnum so a code read off the wire compares equal to its member and a
    member can be written back as a plain number. The names match the
    firmware's so a log line can be searched for in g2core's source.
    """

    # OS, communications and low-level status
    OK = 0
    ERROR = 1
    EAGAIN = 2
    NOOP = 3
    COMPLETE = 4
    SHUTDOWN = 5
    PANIC = 6
    EOL = 7
    EOF = 8
    FILE_NOT_OPEN = 9
    FILE_SIZE_EXCEEDED = 10
    NO_SUCH_DEVICE = 11
    BUFFER_EMPTY = 12
    BUFFER_FULL = 13
    BUFFER_FULL_FATAL = 14
    INITIALIZING = 15
    ENTERING_BOOT_LOADER = 16
    FUNCTION_IS_STUBBED = 17
    ALARM = 18
    NO_DISPLAY = 19

    # Internal errors
    INTERNAL_ERROR = 20
    INTERNAL_RANGE_ERROR = 21
    FLOATING_POINT_ERROR = 22
    DIVIDE_BY_ZERO = 23
    INVALID_ADDRESS = 24
    READ_ONLY_ADDRESS = 25
    INIT_FAILURE = 26
    FAILED_TO_GET_PLANNER_BUFFER = 28
    GENERIC_EXCEPTION_REPORT = 29
    PREP_LINE_MOVE_TIME_IS_INFINITE = 30
    PREP_LINE_MOVE_TIME_IS_NAN = 31
    FLOAT_IS_INFINITE = 32
    FLOAT_IS_NAN = 33
    PERSISTENCE_ERROR = 34
    BAD_STATUS_REPORT_SETTING = 35
    FAILED_GET_PLANNER_BUFFER = 36
    # A placeholder name in error.h, but with a real message; kept under that name.
    ERROR_37 = 37

    # Assertion failures (normally reported together with PANIC)
    SPINDLE_ASSERTION_FAILURE = 86
    EXEC_ALINE_ASSERTION_FAILURE = 87
    BUFFER_FREE_ASSERTION_FAILURE = 88
    STATE_MANAGEMENT_ASSERTION_FAILURE = 89
    CONFIG_ASSERTION_FAILURE = 90
    XIO_ASSERTION_FAILURE = 91
    ENCODER_ASSERTION_FAILURE = 92
    STEPPER_ASSERTION_FAILURE = 93
    PLANNER_ASSERTION_FAILURE = 94
    CANONICAL_MACHINE_ASSERTION_FAILURE = 95
    CONTROLLER_ASSERTION_FAILURE = 96
    STACK_OVERFLOW = 97
    MEMORY_FAULT = 98
    GENERIC_ASSERTION_FAILURE = 99

    # Generic data input errors
    UNRECOGNIZED_NAME = 100
    INVALID_OR_MALFORMED_COMMAND = 101
    BAD_NUMBER_FORMAT = 102
    UNSUPPORTED_TYPE = 103
    PARAMETER_IS_READ_ONLY = 104
    PARAMETER_CANNOT_BE_READ = 105
    COMMAND_NOT_ACCEPTED = 106
    INPUT_EXCEEDS_MAX_LENGTH = 107
    INPUT_LESS_THAN_MIN_VALUE = 108
    INPUT_EXCEEDS_MAX_VALUE = 109
    INPUT_VALUE_RANGE_ERROR = 110
    JSON_SYNTAX_ERROR = 111
    JSON_TOO_MANY_PAIRS = 112
    JSON_OUTPUT_TOO_LONG = 113
    NESTED_TXT_CONTAINER = 114
    MAX_DEPTH_EXCEEDED = 115
    VALUE_TYPE_ERROR = 116
    INPUT_FROM_MUTED_CHANNEL_ERROR = 117
    CHECKSUM_MATCH_FAILED = 118
    LINE_NUMBER_OUT_OF_SEQUENCE = 119
    MISSING_LINE_NUMBER_WITH_CHECKSUM = 120

    # G-code errors and warnings
    GCODE_GENERIC_INPUT_ERROR = 130
    GCODE_COMMAND_UNSUPPORTED = 131
    MCODE_COMMAND_UNSUPPORTED = 132
    GCODE_MODAL_GROUP_VIOLATION = 133
    AXIS_IS_MISSING = 134
    AXIS_CANNOT_BE_PRESENT = 135
    AXIS_IS_INVALID = 136
    AXIS_IS_NOT_CONFIGURED = 137
    AXIS_NUMBER_IS_MISSING = 138
    AXIS_NUMBER_IS_INVALID = 139
    ACTIVE_PLANE_IS_MISSING = 140
    ACTIVE_PLANE_IS_INVALID = 141
    FEEDRATE_NOT_SPECIFIED = 142
    INVERSE_TIME_MODE_CANNOT_BE_USED = 143
    ROTARY_AXIS_CANNOT_BE_USED = 144
    GCODE_G53_WITHOUT_G0_OR_G1 = 145
    REQUESTED_VELOCITY_EXCEEDS_LIMITS = 146
    CUTTER_COMPENSATION_CANNOT_BE_ENABLED = 147
    PROGRAMMED_POINT_SAME_AS_CURRENT_POINT = 148
    SPINDLE_SPEED_BELOW_MINIMUM = 149
    SPINDLE_SPEED_MAX_EXCEEDED = 150
    SPINDLE_MUST_BE_OFF = 151
    SPINDLE_MUST_BE_TURNING = 152
    ARC_SPECIFICATION_ERROR = 153
    ARC_HAS_IMPOSSIBLE_CENTER_POINT = 154
    ARC_HAS_ROTARY_AXIS = 155
    ARC_AXIS_MISSING_FOR_SELECTED_PLANE = 156
    ARC_OFFSETS_MISSING_FOR_SELECTED_PLANE = 157
    ARC_RADIUS_OUT_OF_TOLERANCE = 158
    ARC_ENDPOINT_IS_STARTING_POINT = 159
    P_WORD_IS_MISSING = 160
    P_WORD_IS_INVALID = 161
    P_WORD_IS_ZERO = 162
    P_WORD_IS_NEGATIVE = 163
    P_WORD_IS_NOT_AN_INTEGER = 164
    P_WORD_IS_NOT_VALID_TOOL_NUMBER = 165
    D_WORD_IS_MISSING = 166
    D_WORD_IS_INVALID = 167
    E_WORD_IS_MISSING = 168
    E_WORD_IS_INVALID = 169
    H_WORD_IS_MISSING = 170
    H_WORD_IS_INVALID = 171
    L_WORD_IS_MISSING = 172
    L_WORD_IS_INVALID = 173
    Q_WORD_IS_MISSING = 174
    Q_WORD_IS_INVALID = 175
    R_WORD_IS_MISSING = 176
    R_WORD_IS_INVALID = 177
    S_WORD_IS_MISSING = 178
    S_WORD_IS_INVALID = 179
    T_WORD_IS_MISSING = 180
    T_WORD_IS_INVALID = 181

    # g2core errors and warnings
    GENERIC_ERROR = 200
    MINIMUM_LENGTH_MOVE = 201
    MINIMUM_TIME_MOVE = 202
    LIMIT_SWITCH_HIT = 203
    COMMAND_REJECTED_BY_ALARM = 204
    COMMAND_REJECTED_BY_SHUTDOWN = 205
    COMMAND_REJECTED_BY_PANIC = 206
    KILL_JOB = 207
    NO_GPIO = 208
    TEMPERATURE_CONTROL_ERROR = 209
    G29_NOT_CONFIGURED = 210
    SOFT_LIMIT_EXCEEDED = 220
    SOFT_LIMIT_EXCEEDED_XMIN = 221
    SOFT_LIMIT_EXCEEDED_XMAX = 222
    SOFT_LIMIT_EXCEEDED_YMIN = 223
    SOFT_LIMIT_EXCEEDED_YMAX = 224
    SOFT_LIMIT_EXCEEDED_ZMIN = 225
    SOFT_LIMIT_EXCEEDED_ZMAX = 226
    SOFT_LIMIT_EXCEEDED_AMIN = 227
    SOFT_LIMIT_EXCEEDED_AMAX = 228
    SOFT_LIMIT_EXCEEDED_BMIN = 229
    SOFT_LIMIT_EXCEEDED_BMAX = 230
    SOFT_LIMIT_EXCEEDED_CMIN = 231
    SOFT_LIMIT_EXCEEDED_CMAX = 232
    SOFT_LIMIT_EXCEEDED_ARC = 233
    HOMING_CYCLE_FAILED = 240
    HOMING_ERROR_BAD_OR_NO_AXIS = 241
    HOMING_ERROR_ZERO_SEARCH_VELOCITY = 242
    HOMING_ERROR_ZERO_LATCH_VELOCITY = 243
    HOMING_ERROR_TRAVEL_MIN_MAX_IDENTICAL = 244
    HOMING_ERROR_NEGATIVE_LATCH_BACKOFF = 245
    HOMING_ERROR_HOMING_INPUT_MISCONFIGURED = 246
    HOMING_ERROR_MUST_CLEAR_SWITCHES_BEFORE_HOMING = 247
    PROBE_CYCLE_FAILED = 250
    PROBE_TRAVEL_TOO_SMALL = 251
    NO_PROBE_INPUT_CONFIGURED = 252
    MULTIPLE_PROBE_SWITCHES_CONFIGURED = 253
    PROBE_IS_ALREADY_TRIPPED = 254


# code -> the firmware's message text, verbatim from error.h (fb 101.x).
# Exactly one entry per Status member; the tests hold the two together.
MESSAGES: Final[Mapping[int, str]] = MappingProxyType(
    {
        0: "OK",
        1: "Error",
        2: "Eagain",
        3: "No operation performed",
        4: "Completed operation",
        5: "System shutdown",
        6: "System panic",
        7: "End of line",
        8: "End of file",
        9: "File not open",
        10: "Max file size exceeded",
        11: "No such device",
        12: "Buffer empty",
        13: "Buffer full non-fatal",
        14: "Buffer full FATAL",
        15: "Initializing",
        16: "Entering boot loader",
        17: "Function is stubbed",
        18: "System alarm",
        19: "19",
        20: "Internal error",
        21: "Internal range error",
        22: "Floating point error",
        23: "Divide by zero",
        24: "Invalid Address",
        25: "Read-only address",
        26: "Initialization failure",
        28: "Failed to get planner buffer",
        29: "Generic exception report",
        30: "Move time is infinite",
        31: "Move time is NAN",
        32: "Float is infinite",
        33: "Float is NAN",
        34: "Persistence error",
        35: "Bad status report setting",
        36: "Failed to get planner buffer",
        37: "Backplan hit running buffer",
        86: "Spindle assertion failure",
        87: "mp_exec_aline() assertion failure",
        88: "Buffer free assertion failure",
        89: "State management assertion failure",
        90: "Config assertion failure",
        91: "XIO assertion failure",
        92: "Encoder assertion failure",
        93: "Stepper assertion failure",
        94: "Planner assertion failure",
        95: "Canonical machine assertion failure",
        96: "Controller assertion failure",
        97: "Stack overflow detected",
        98: "Memory fault detected",
        99: "Generic assertion failure",
        100: "Unrecognized command or config name",
        101: "Invalid or malformed command",
        102: "Bad number format",
        103: "Unsupported number or JSON type",
        104: "Parameter is read-only",
        105: "Parameter cannot be read",
        106: "Command not accepted",
        107: "Input exceeds max length",
        108: "Input less than minimum value",
        109: "Input exceeds maximum value",
        110: "Input value range error",
        111: "JSON syntax error",
        112: "JSON has too many pairs",
        113: "JSON string too long",
        114: "JSON txt fields cannot be nested",
        115: "JSON maximum nesting depth exceeded",
        116: "JSON value does not agree with variable type",
        117: "Input from a muted channel was ignored",
        118: "The provided checksum didn't match",
        119: "The provided line number was out of sequence",
        120: "120",
        130: "Generic Gcode input error",
        131: "Gcode command unsupported",
        132: "M code unsupported",
        133: "Gcode modal group violation",
        134: "Axis word missing",
        135: "Axis cannot be present",
        136: "Axis invalid for this command",
        137: "Axis disabled",
        138: "Axis target position missing",
        139: "Axis target position invalid",
        140: "Selected plane missing",
        141: "Selected plane invalid",
        142: "Feedrate not specified",
        143: "Inverse time mode cannot be used with this command",
        144: "Rotary axes cannot be used with this command",
        145: "G0 or G1 must be active for G53",
        146: "Requested velocity exceeds limits",
        147: "Cutter compensation cannot be enabled",
        148: "Programmed point same as current point",
        149: "Spindle speed below minimum",
        150: "Spindle speed exceeded maximum",
        151: "Spindle must be off for this command",
        152: "Spindle must be turning for this command",
        153: "Arc specification error",
        154: "Arc specification error - impossible center point",
        155: "Arc specification error - arc has rotary axis(es)",
        156: "Arc specification error - missing axis(es)",
        157: "Arc specification error - missing offset(s)",
        158: "Arc specification error - radius arc out of tolerance",
        159: "Arc specification error - endpoint is starting point",
        160: "P word missing",
        161: "P word invalid",
        162: "P word zero",
        163: "P word negative",
        164: "P word not an integer",
        165: "P word not a valid tool number",
        166: "D word missing",
        167: "D word invalid",
        168: "E word missing",
        169: "E word invalid",
        170: "H word missing",
        171: "H word invalid",
        172: "L word missing",
        173: "L word invalid",
        174: "Q word missing",
        175: "Q word invalid",
        176: "R word missing",
        177: "R word invalid",
        178: "S word missing",
        179: "S word invalid",
        180: "T word missing",
        181: "T word invalid",
        200: "Generic error",
        201: "Move < min length",
        202: "Move < min time",
        203: "Limit hit [$clear to reset, $lim=0 to override]",
        204: "Command rejected by ALARM [$clear to reset]",
        205: "Command rejected by SHUTDOWN [$clear to reset]",
        206: "Command rejected by PANIC [^x to reset]",
        207: "Kill job",
        208: "No GPIO for this value",
        209: "209",
        210: "Marlin G29 command was not configured at compile-time",
        220: "Soft limit",
        221: "Soft limit - X min",
        222: "Soft limit - X max",
        223: "Soft limit - Y min",
        224: "Soft limit - Y max",
        225: "Soft limit - Z min",
        226: "Soft limit - Z max",
        227: "Soft limit - A min",
        228: "Soft limit - A max",
        229: "Soft limit - B min",
        230: "Soft limit - B max",
        231: "Soft limit - C min",
        232: "Soft limit - C max",
        233: "Soft limit during arc",
        240: "Homing cycle failed",
        241: "Homing Err - Bad or no axis specified",
        242: "Homing Err - Search velocity is zero",
        243: "Homing Err - Latch velocity is zero",
        244: "Homing Err - Travel min & max are the same",
        245: "245",
        246: "Homing Err - Homing input is misconfigured",
        247: "Homing Err - Must clear switches before homing",
        250: "Probe cycle failed",
        251: "Probe travel is too small",
        252: "No probe switch configured",
        253: "Multiple probe switches configured",
        254: "Probe is already tripped",
    }
)


@dataclass(frozen=True, slots=True)
class StatusInfo:
    """A status code with its name and message, for logs and API answers in one value."""

    code: int
    name: str
    message: str


def message(code: int) -> str:
    """The firmware's message for `code`, or a fallback that still shows the number.

    Never raises: a code comes from the board, and a board running other
    firmware (or a newer build) may send one we do not know; reporting it must
    not turn into a second failure.
    """
    text = MESSAGES.get(code)
    if text is None:
        return f"Unknown status code {code}"
    return text


def name(code: int) -> str:
    """The member name for `code` (e.g. "KILL_JOB"), or "UNKNOWN_<code>". Never raises."""
    try:
        return Status(code).name
    except ValueError:
        return f"UNKNOWN_{code}"


def lookup(code: int) -> StatusInfo:
    """Code, name and message together. Never raises, for the same reason as `message()`."""
    return StatusInfo(code=int(code), name=name(code), message=message(code))


# What an exception report announces, before the status report that follows says so:
# the codes g2core's own alarm, shutdown and panic paths raise (cm_alarm, cm_shutdown,
# cm_panic in synthetos/g2 edge-preview and master, g2core/*.cpp; see docs/protocol.md).
# Values are the lockout's name in hostd.protocol.states.MachineState.
LOCKOUT_RAISED_BY: dict[int, str] = {
    # cm_alarm: host or input (alarm.cpp, canonical_machine.cpp), limit switch
    # (controller.cpp), soft limits (canonical_machine.cpp, plan_arc.cpp), probing
    # (cycle_probing.cpp), arc offsets (plan_arc.cpp), heaters (temperature.cpp), and
    # an encoder that stopped answering (kinematics_four_cable.h).
    Status.ALARM: "ALARM",
    Status.LIMIT_SWITCH_HIT: "ALARM",
    **dict.fromkeys(range(220, 234), "ALARM"),
    Status.PROBE_CYCLE_FAILED: "ALARM",
    Status.PROBE_TRAVEL_TOO_SMALL: "ALARM",
    Status.NO_PROBE_INPUT_CONFIGURED: "ALARM",
    Status.PROBE_IS_ALREADY_TRIPPED: "ALARM",
    Status.FEEDRATE_NOT_SPECIFIED: "ALARM",
    Status.AXIS_IS_MISSING: "ALARM",
    Status.ARC_OFFSETS_MISSING_FOR_SELECTED_PLANE: "ALARM",
    Status.TEMPERATURE_CONTROL_ERROR: "ALARM",
    Status.ENCODER_ASSERTION_FAILURE: "ALARM",
    # cm_shutdown: host, e-stop input (safety_manager.h).
    Status.SHUTDOWN: "SHUTDOWN",
    # cm_panic: host or input, the *_test_assertions() of each module, the planner,
    # stepper and report paths that "never" fail, and an arc with no plane.
    Status.PANIC: "PANIC",
    Status.BUFFER_FULL_FATAL: "PANIC",
    Status.INTERNAL_ERROR: "PANIC",
    Status.PREP_LINE_MOVE_TIME_IS_INFINITE: "PANIC",
    Status.PREP_LINE_MOVE_TIME_IS_NAN: "PANIC",
    Status.FAILED_GET_PLANNER_BUFFER: "PANIC",
    **dict.fromkeys((89, 90, 91, 93, 94, 95, 96), "PANIC"),  # assertion failures
    Status.ACTIVE_PLANE_IS_MISSING: "PANIC",
    Status.ACTIVE_PLANE_IS_INVALID: "PANIC",
}
