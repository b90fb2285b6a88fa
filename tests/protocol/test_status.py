"""The g2core status table: names other code relies on, error.h spot checks, no raising."""

from __future__ import annotations

import dataclasses

import pytest

from hostd.protocol.status import (
    LOCKOUT_RAISED_BY,
    MESSAGES,
    Status,
    StatusInfo,
    lookup,
    message,
    name,
)


@pytest.mark.parametrize(
    ("member", "code"),
    [
        (Status.OK, 0),
        (Status.ERROR, 1),
        (Status.EAGAIN, 2),
        (Status.SHUTDOWN, 5),
        (Status.PANIC, 6),
        (Status.ALARM, 18),
        (Status.UNRECOGNIZED_NAME, 100),
        (Status.JSON_SYNTAX_ERROR, 111),
        (Status.GCODE_COMMAND_UNSUPPORTED, 131),
        (Status.MCODE_COMMAND_UNSUPPORTED, 132),
        (Status.FEEDRATE_NOT_SPECIFIED, 142),
        (Status.LIMIT_SWITCH_HIT, 203),
        (Status.COMMAND_REJECTED_BY_ALARM, 204),
        (Status.COMMAND_REJECTED_BY_SHUTDOWN, 205),
        (Status.COMMAND_REJECTED_BY_PANIC, 206),
        (Status.KILL_JOB, 207),
        (Status.SOFT_LIMIT_EXCEEDED, 220),
        (Status.SOFT_LIMIT_EXCEEDED_XMIN, 221),
        (Status.HOMING_CYCLE_FAILED, 240),
        (Status.PROBE_CYCLE_FAILED, 250),
    ],
)
def test_names_other_code_relies_on(member: Status, code: int) -> None:
    assert member == code
    assert Status(code) is member


@pytest.mark.parametrize(
    ("code", "expected_name", "word"),
    [
        (204, "COMMAND_REJECTED_BY_ALARM", "alarm"),
        (205, "COMMAND_REJECTED_BY_SHUTDOWN", "shutdown"),
        (206, "COMMAND_REJECTED_BY_PANIC", "panic"),
        (207, "KILL_JOB", "kill"),
    ],
)
def test_rejection_and_kill_codes(code: int, expected_name: str, word: str) -> None:
    assert name(code) == expected_name
    assert word in message(code).lower()
    info = lookup(code)
    assert info == StatusInfo(code, expected_name, message(code))


@pytest.mark.parametrize(
    ("code", "expected_name", "text"),
    [
        (0, "OK", "OK"),
        (18, "ALARM", "System alarm"),
        (100, "UNRECOGNIZED_NAME", "Unrecognized command or config name"),
        (108, "INPUT_LESS_THAN_MIN_VALUE", "Input less than minimum value"),
        (111, "JSON_SYNTAX_ERROR", "JSON syntax error"),
        (130, "GCODE_GENERIC_INPUT_ERROR", "Generic Gcode input error"),
        (131, "GCODE_COMMAND_UNSUPPORTED", "Gcode command unsupported"),
        (132, "MCODE_COMMAND_UNSUPPORTED", "M code unsupported"),
        (142, "FEEDRATE_NOT_SPECIFIED", "Feedrate not specified"),
        (153, "ARC_SPECIFICATION_ERROR", "Arc specification error"),
        (203, "LIMIT_SWITCH_HIT", "Limit hit [$clear to reset, $lim=0 to override]"),
        (204, "COMMAND_REJECTED_BY_ALARM", "Command rejected by ALARM [$clear to reset]"),
        (206, "COMMAND_REJECTED_BY_PANIC", "Command rejected by PANIC [^x to reset]"),
        (220, "SOFT_LIMIT_EXCEEDED", "Soft limit"),
        (221, "SOFT_LIMIT_EXCEEDED_XMIN", "Soft limit - X min"),
        (230, "SOFT_LIMIT_EXCEEDED_BMAX", "Soft limit - B max"),
        (240, "HOMING_CYCLE_FAILED", "Homing cycle failed"),
        (250, "PROBE_CYCLE_FAILED", "Probe cycle failed"),
        (254, "PROBE_IS_ALREADY_TRIPPED", "Probe is already tripped"),
    ],
)
def test_spot_checks_against_error_h(code: int, expected_name: str, text: str) -> None:
    assert name(code) == expected_name
    assert message(code) == text


def test_every_member_has_a_message_and_every_message_a_member() -> None:
    assert set(MESSAGES) == {int(member) for member in Status}
    for member in Status:
        assert message(member)
        assert message(member) == MESSAGES[member]
        assert name(member) == member.name


def test_codes_are_bytes() -> None:
    # stat_t is a uint8_t on the board: anything else cannot come from g2core.
    assert all(0 <= member <= 255 for member in Status)


def test_unused_placeholders_are_unknown() -> None:
    for code in (27, 38, 85, 121, 182, 199, 211, 234, 248, 255):
        assert code not in MESSAGES
        assert name(code) == f"UNKNOWN_{code}"
        assert message(code) == f"Unknown status code {code}"


def test_37_keeps_its_message() -> None:
    assert name(37) == "ERROR_37"
    assert message(37) == "Backplan hit running buffer"


@pytest.mark.parametrize(
    "code", [*range(-5, 300), 2**31, 2**63, 2**64 + 1, -(2**63), 10**30, -(10**30)]
)
def test_lookups_never_raise(code: int) -> None:
    text = message(code)
    label = name(code)
    info = lookup(code)
    assert text
    assert label
    assert info == StatusInfo(code, label, text)
    assert str(code) in text or code in MESSAGES


def test_unknown_fallbacks() -> None:
    assert message(123) == "Unknown status code 123"
    assert name(123) == "UNKNOWN_123"
    assert name(-1) == "UNKNOWN_-1"
    assert lookup(300) == StatusInfo(300, "UNKNOWN_300", "Unknown status code 300")


def test_lookup_gives_a_plain_int_and_is_frozen() -> None:
    info = lookup(Status.KILL_JOB)
    assert type(info.code) is int
    assert info.code == 207
    with pytest.raises(dataclasses.FrozenInstanceError):
        info.code = 1  # type: ignore[misc]


def test_table_is_read_only() -> None:
    with pytest.raises(TypeError):
        MESSAGES[0] = "changed"  # type: ignore[index]


# Codes g2core's cm_alarm / cm_shutdown / cm_panic raise (issue 12, item 6; the call
# sites are cited in docs/protocol.md).
@pytest.mark.parametrize(
    ("code", "lockout"),
    [
        (18, "ALARM"), (203, "ALARM"), (221, "ALARM"), (233, "ALARM"),
        (250, "ALARM"), (251, "ALARM"), (252, "ALARM"), (254, "ALARM"),
        (142, "ALARM"), (134, "ALARM"), (157, "ALARM"), (209, "ALARM"),
        (92, "ALARM"),  # an encoder that stopped answering: kinematics raise an alarm
        (5, "SHUTDOWN"),
        (6, "PANIC"), (14, "PANIC"), (20, "PANIC"), (30, "PANIC"), (31, "PANIC"),
        (36, "PANIC"), (89, "PANIC"), (96, "PANIC"), (140, "PANIC"), (141, "PANIC"),
    ],
)  # fmt: skip
def test_exception_codes_the_firmware_raises_as_lockouts(code: int, lockout: str) -> None:
    assert LOCKOUT_RAISED_BY[code] == lockout


@pytest.mark.parametrize("code", [0, 40, 100, 207, 113, 204, 205, 206, 240])
def test_other_exception_codes_announce_no_lockout(code: int) -> None:
    assert code not in LOCKOUT_RAISED_BY
