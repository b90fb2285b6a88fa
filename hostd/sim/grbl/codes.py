"""The numbers and texts grbl prints: status codes, alarm codes, feedback messages.

Numbers from grblHAL/core errors.h and alarms.h (classic grbl 1.1's own
codes are the same up to error 37 and alarm 9, gnea/grbl
doc/csv/error_codes_en_US.csv and alarm_codes_en_US.csv). Only the ones the
simulator can produce are named. Message texts from grblHAL/core messages.c
(Message_*), identical to gnea/grbl report.c report_feedback_message() for
the ones both have.
"""

from __future__ import annotations

from enum import Enum, IntEnum


class Error(IntEnum):
    """`error:N` (grblHAL errors.h status_code_t)."""

    OK = 0
    EXPECTED_COMMAND_LETTER = 1
    BAD_NUMBER_FORMAT = 2
    INVALID_STATEMENT = 3
    NEGATIVE_VALUE = 4
    HOMING_DISABLED = 5  # classic: STATUS_SETTING_DISABLED, "Homing not enabled"
    IDLE_ERROR = 8
    SYSTEM_GC_LOCK = 9  # "G-code locked out during alarm or jog state"
    SOFT_LIMIT_ERROR = 10
    OVERFLOW = 11  # line longer than the line buffer
    CHECK_DOOR = 13
    TRAVEL_EXCEEDED = 15  # a jog target outside the soft limits
    INVALID_JOG_COMMAND = 16
    UNSUPPORTED_COMMAND = 20
    MODAL_GROUP_VIOLATION = 21
    UNDEFINED_FEED_RATE = 22
    COMMAND_VALUE_NOT_INTEGER = 23
    AXIS_COMMAND_CONFLICT = 24
    WORD_REPEATED = 25
    NO_AXIS_WORDS = 26
    INVALID_LINE_NUMBER = 27
    VALUE_WORD_MISSING = 28
    G53_INVALID_MOTION_MODE = 30
    AXIS_WORDS_EXIST = 31
    NO_AXIS_WORDS_IN_PLANE = 32
    INVALID_TARGET = 33
    ARC_RADIUS_ERROR = 34
    UNUSED_WORDS = 36
    G43_DYNAMIC_AXIS_ERROR = 37
    HOMING_REQUIRED = 46  # grblHAL only
    ESTOP = 50  # grblHAL only
    NOT_ALLOWED_CRITICAL_EVENT = 79  # grblHAL only: "$X" and friends after ALARM:1/2/10


class Alarm(IntEnum):
    """`ALARM:N` (grblHAL alarms.h alarm_code_t)."""

    HARD_LIMIT = 1
    SOFT_LIMIT = 2
    ABORT_CYCLE = 3  # reset while in motion
    PROBE_FAIL_INITIAL = 4
    PROBE_FAIL_CONTACT = 5
    HOMING_FAIL_RESET = 6
    ESTOP = 10  # grblHAL only (classic grbl's 10 is a dual-axis homing failure)
    HOMING_REQUIRED = 11  # grblHAL only


# grblHAL alarms.h alarm_is_critical(): these block everything but reset,
# status reports and `$` commands flagged allow_blocking (protocol.c).
CRITICAL = frozenset({Alarm.HARD_LIMIT, Alarm.SOFT_LIMIT, Alarm.ESTOP})


class Msg(Enum):
    """`[MSG:...]` feedback messages (grblHAL messages.c)."""

    NONE = ""
    CRITICAL_EVENT = "Reset to continue"
    ALARM_LOCK = "'$H'|'$X' to unlock"
    ALARM_UNLOCK = "Caution: Unlocked"
    ENABLED = "Enabled"
    DISABLED = "Disabled"
    SAFETY_DOOR_AJAR = "Check Door"
    PROGRAM_END = "Pgm End"
    ESTOP = "Emergency stop - clear, then reset to continue"
    HOMING_CYCLE_REQUIRED = "Homing cycle required"
