"""Why the host refuses to send something: the one enum, and the error that carries it.

A leaf module, so that every reader in `hostd.protocol` (relaxed JSON,
text commands, G-code words, settings) can refuse in the same words without
importing each other. `hostd.protocol.commands` re-exports both names.
"""

from __future__ import annotations

from enum import StrEnum


class Refusal(StrEnum):
    """Why a line (or a value) may never be sent; clients see it as `data.refusal`."""

    EMPTY = "empty"
    NUL = "nul"
    TOO_LONG = "too-long"
    LINE_BREAK = "line-break"
    CONTROL_CHAR = "control-char"
    NOT_TEXT = "not-text"
    REALTIME = "realtime"
    TAPE_MARK = "tape-mark"
    UBER_GROUP = "uber-group"
    HELP = "help"
    BOOTLOADER = "bootloader"
    # The host cannot read the line exactly as the board will, so cannot classify it.
    UNREADABLE = "unreadable"
    # The same name twice: the board runs both pairs, in order.
    DUPLICATE_KEY = "duplicate-key"
    # Not finite, out of bounds, or written so the board would read another number.
    BAD_NUMBER = "bad-number"
    # JSON inside a G-code comment, which the board runs as a command of its own.
    ACTIVE_COMMENT = "active-comment"
    # A name that is not a setting, or a setting the daemon owns.
    RESERVED_KEY = "reserved-key"
    # A setting's text value the board would read differently.
    BAD_VALUE = "bad-value"
    # A maintenance command (protocol/maintenance.py): wipes, stores, sleeps or jogs
    # absurdly; only `machine.maintenance` sends it, and only where the config allows.
    MAINTENANCE = "maintenance"


class InvalidCommand(ValueError):
    """The host was asked to send something the controller must never receive.

    Always the caller's invalid input: it carries the API's -32602 and the
    refusal as `data`, so it is answered the same wherever it is raised (the
    API answers any error with an integer `code`). A ValueError, so that a
    pydantic validator raising it is a -32602 too.
    """

    code = -32602

    def __init__(self, refusal: Refusal, message: str) -> None:
        super().__init__(message)
        self.refusal = refusal
        self.message = message

    @property
    def data(self) -> dict[str, str]:
        return {"refusal": self.refusal.value}
