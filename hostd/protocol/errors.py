"""Errors a machine request can end in, each with its api.md error code."""

from __future__ import annotations

from typing import Any


class MachineError(Exception):
    """A request could not be done; `code` and `data` go to the client as they are."""

    code = 1000

    def __init__(self, message: str, data: Any = None) -> None:
        super().__init__(message)
        self.message = message
        self.data = data


class Rejected(MachineError):
    """Refused by the command class table: the controller is in ALARM, SHUTDOWN or PANIC."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.code = status  # 204, 205 or 206


class NotConnected(MachineError):
    code = 1002


class Busy(MachineError):
    code = 1003


class ControllerError(MachineError):
    """The controller answered with a non-zero status; status 0 where it gave none (a
    line its reset discarded, a cycle that ended in an alarm), and then the message is
    said alone, not as an answer of 0."""

    code = 1005

    def __init__(self, status: int, message: str) -> None:
        text = f"controller answered {status}: {message}" if status else message
        super().__init__(text, {"status": status, "msg": message})
        self.status = status


class ControllerTimeout(MachineError):
    code = 1006


class FaultActive(MachineError):
    """An un-overridden fault forbids this request; `data` lists the fault ids."""

    code = 1007
