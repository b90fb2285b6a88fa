"""A machine's fault table (seed 001, behaviour.md "Faults"): one table of rules.

Everything that decides how a fault behaves lives in `RULES`: its severity,
whether an operator may override it, and what clears it. `FaultTable` holds
the current state of the ten faults of one machine and applies the rules; it
does no I/O and reads no clock (`now`, a `time.time()` value, is passed in),
so every rule is testable with plain calls.

Three ways a fault clears, never mixed:
- `SIGNAL`: it follows a condition (an input, a threshold, the controller's
  SHUTDOWN state) and goes away only when the condition does. Software can
  neither raise nor clear it except by reporting the condition (`set`).
- `SOFTWARE`: raised by the daemon (`raise_`), cleared by `fault.clear`
  (`clear`) or by `machine.reset` (`reset`).
- `RESET`: raised by the daemon, cleared only by `machine.reset`.

Overrides are the seed's `oo`/`oc` variables: an operator's setting, kept
while the fault comes and goes and across `machine.reset`; they never change
whether a fault is active, only whether it blocks and how the indicator
shows it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from datetime import UTC, datetime
from enum import Enum, StrEnum
from typing import Any


class Severity(StrEnum):
    RECOVERABLE = "recoverable"  # reported, nothing more
    JOB = "job"  # ruins a job in progress
    HARDWARE = "hardware"  # imminent hardware failure


class Clears(Enum):
    SIGNAL = "signal"  # only when its condition goes away; never by software
    SOFTWARE = "software"  # fault.clear (and machine.reset)
    RESET = "reset"  # only machine.reset


class Indicator(StrEnum):
    NORMAL = "normal"
    WARNING = "warning"
    ALERT = "alert"


@dataclass(frozen=True, slots=True)
class Rule:
    severity: Severity
    overridable: bool
    clears: Clears
    text: str  # what the fault means, as the operator reads it
    with_value: str | None = None  # the same with its value; "{value}" is replaced

    def message(self, value: Any, detail: str | None) -> str:
        text = self.text
        if value is not None and self.with_value is not None:
            text = self.with_value.format(value=value)
        return f"{text}: {detail}" if detail else text


_SIG, _SW, _RST = Clears.SIGNAL, Clears.SOFTWARE, Clears.RESET
_REC, _JOB, _HW = Severity.RECOVERABLE, Severity.JOB, Severity.HARDWARE

# behaviour.md "Faults", in its order (which is the order of fault.list).
RULES: dict[str, Rule] = {
    "estop": Rule(_JOB, False, _SIG, "e-stop active"),
    "lid_open": Rule(_JOB, True, _SIG, "lid open while the main laser is selected"),
    "lid_closed": Rule(_REC, True, _SIG, "lid closed while the visible laser is selected"),
    "water_flow": Rule(
        _HW, True, _SIG, "coolant flow stopped or below minimum", "coolant flow low ({value})"
    ),
    "water_temp": Rule(
        _HW, True, _SIG, "coolant temperature above maximum", "coolant temperature high ({value})"
    ),
    "serial": Rule(
        _JOB, False, _SW, "serial link error", "serial link error after {value} lines processed"
    ),
    "lexical": Rule(_JOB, False, _SW, "controller output could not be parsed"),
    "syntax": Rule(_JOB, False, _RST, "the controller rejected a line as malformed"),
    "underflow": Rule(_JOB, False, _SW, "the controller ran out of moves mid-job"),
    "internal": Rule(_JOB, False, _RST, "hostd broke one of its own rules for this machine"),
}
FAULT_IDS: tuple[str, ...] = tuple(RULES)

# Why software cannot clear a fault, by how it does clear.
_NOT_CLEARABLE = {
    Clears.SIGNAL: "{id} clears only when its condition goes away",
    Clears.RESET: "{id} clears only with machine.reset",
}
_NOT_CLEARABLE_BY_ID = {"estop": "estop clears only when the input is released"}

INVALID_PARAMS = -32602


class FaultError(Exception):
    """A client asked for something the rules forbid (or named no fault at all)."""

    def __init__(self, message: str, code: int = INVALID_PARAMS) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


@dataclass(frozen=True, slots=True)
class Fault:
    """One fault as api.md's fault object has it."""

    id: str
    severity: Severity
    active: bool
    overridden: bool
    overridable: bool
    since: str | None  # ISO 8601 UTC while active
    value: Any
    message: str

    @property
    def blocking(self) -> bool:
        """Stops a running job and refuses job.start (error 1007)."""
        return self.active and not self.overridden and self.severity != Severity.RECOVERABLE

    def to_json(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "severity": self.severity.value,
            "active": self.active,
            "overridden": self.overridden,
            "overridable": self.overridable,
            "since": self.since,
            "value": self.value,
            "message": self.message,
            # Added (api.md's fault object): how it ends, so that a client can offer
            # the way out: "signal", "software" (fault.clear) or "reset" (machine.reset).
            "clears": RULES[self.id].clears.value,
        }


def timestamp(now: float) -> str:
    """A `time.time()` value as the API writes times (as jobstore does)."""
    stamp = datetime.fromtimestamp(now, UTC).isoformat(timespec="milliseconds")
    return stamp.replace("+00:00", "Z")


class FaultTable:
    """The ten faults of one machine, all inactive and not overridden at first."""

    def __init__(self) -> None:
        self._faults: dict[str, Fault] = {fid: _inactive(fid, False) for fid in RULES}

    # --- reading

    def get(self, fault_id: str) -> Fault:
        return self._faults[self._known(fault_id)]

    def all(self) -> list[Fault]:
        return list(self._faults.values())

    def active(self) -> list[Fault]:
        return [f for f in self._faults.values() if f.active]

    def blocking(self) -> list[Fault]:
        """Active, not overridden, severity job or hardware (behaviour.md)."""
        return [f for f in self._faults.values() if f.blocking]

    def indicator(self) -> Indicator:
        active = self.active()
        if any(not f.overridden for f in active):
            return Indicator.ALERT
        if active:
            return Indicator.WARNING
        return Indicator.NORMAL

    # --- what the daemon observes

    def set(
        self,
        fault_id: str,
        active: bool,
        *,
        value: Any = None,
        message: str | None = None,
        now: float,
    ) -> Fault | None:
        """A signal fault follows its condition; the fault if anything changed, else None.

        Becoming active sets `since`; staying active keeps it and takes the new
        value and message; clearing drops all three.
        """
        if self._rule(fault_id).clears != Clears.SIGNAL:
            raise ValueError(f"{fault_id} is not a signal fault: use raise_(), not set()")
        if not active:
            return self._deactivate(fault_id)
        return self._activate(fault_id, value, message, now)

    def raise_(
        self, fault_id: str, *, value: Any = None, message: str | None = None, now: float
    ) -> Fault | None:
        """The daemon detected a software fault; the fault if anything changed, else None.

        Raising an active fault again keeps its `since` and takes the new value
        and message.
        """
        if self._rule(fault_id).clears == Clears.SIGNAL:
            raise ValueError(f"{fault_id} follows a signal: use set(), not raise_()")
        return self._activate(fault_id, value, message, now)

    # --- what clients ask for

    def clear(self, fault_id: str) -> Fault:
        """fault.clear: only faults software may clear; an inactive one is left as it is."""
        rule = RULES[self._known(fault_id)]
        if rule.clears != Clears.SOFTWARE:
            reason = _NOT_CLEARABLE_BY_ID.get(fault_id) or _NOT_CLEARABLE[rule.clears]
            raise FaultError(reason.format(id=fault_id))
        self._deactivate(fault_id)
        return self._faults[fault_id]

    def override(self, fault_id: str, on: bool) -> Fault:
        """fault.override: sets or unsets the override; `active` is untouched."""
        if not RULES[self._known(fault_id)].overridable:
            raise FaultError(f"{fault_id} cannot be overridden")
        self._store(dataclasses.replace(self._faults[fault_id], overridden=on))
        return self._faults[fault_id]

    def reset(self) -> list[Fault]:
        """machine.reset: the back end restarts, so every fault software raised is gone.

        Signal faults stay as their conditions say; overrides stay. Returns the
        faults that changed.
        """
        changed = (self._deactivate(fid) for fid, r in RULES.items() if r.clears != Clears.SIGNAL)
        return [fault for fault in changed if fault is not None]

    # --- internals

    def _known(self, fault_id: str) -> str:
        if fault_id not in RULES:
            raise FaultError(f"unknown fault {fault_id!r} (known: {', '.join(FAULT_IDS)})")
        return fault_id

    def _rule(self, fault_id: str) -> Rule:
        """The rule of a fault the daemon itself names: an unknown one is a bug here."""
        rule = RULES.get(fault_id)
        if rule is None:
            raise ValueError(f"unknown fault {fault_id!r}")
        return rule

    def _activate(self, fault_id: str, value: Any, detail: str | None, now: float) -> Fault | None:
        old = self._faults[fault_id]
        new = dataclasses.replace(
            old,
            active=True,
            since=old.since if old.active else timestamp(now),
            value=value,
            message=RULES[fault_id].message(value, detail),
        )
        return self._store(new)

    def _deactivate(self, fault_id: str) -> Fault | None:
        return self._store(_inactive(fault_id, self._faults[fault_id].overridden))

    def _store(self, new: Fault) -> Fault | None:
        """Keep `new`; it is returned only if it differs from what was there."""
        if new == self._faults[new.id]:
            return None
        self._faults[new.id] = new
        return new


def _inactive(fault_id: str, overridden: bool) -> Fault:
    rule = RULES[fault_id]
    return Fault(
        id=fault_id,
        severity=rule.severity,
        active=False,
        overridden=overridden,
        overridable=rule.overridable,
        since=None,
        value=None,
        message=rule.text,
    )
