"""The board's configuration: what `{key:n}` and `$key` read and `{key:v}` writes.

A small profile ("settings_sim.h"): communication settings (ej, jv, js, sv,
si, qv), alarm enables (sl soft limits, lim limit switches, saf interlock),
per-axis velocity and travel (xvm xfr xtn xtm, ...), the read-only identity
of the banner, and the status report list. The defaults are g2core's
(g2core.md sections 4, 10, 11), except that this machine has soft limits on.
"""

from __future__ import annotations

from typing import Any

from hostd.protocol.g2builds import OVERRIDE_RANGES, OVERRIDES_RENAMED, Build
from hostd.protocol.status import Status
from hostd.sim import reports
from hostd.sim.config import AXES, SimConfig
from hostd.sim.relaxed import Value

FV = 0.99
BOARD_ID = "sim0-0000-0000-001"
MIN_SI_MS = 100.0  # STATUS_REPORT_MIN_MS
JV_MAX = 6  # JV_EXCEPTIONS
_RANGES = {"ej": (0, 2), "jv": (0, JV_MAX), "sv": (0, 2), "qv": (0, 2)}
_RANGES |= {"sl": (0, 1), "lim": (0, 1), "saf": (0, 1)}
# `prbin`: the digital input G38.x reads (canonical_machine.cpp cm_set_probe_input:
# 0..D_IN_CHANNELS; 0 is none). This profile wires the probe to in5, as
# settings_cheapo_laser.h does (PROBING_INPUT 5).
_RANGES |= {"prbin": (0, reports.DIGITAL_INPUTS)}
PROBING_INPUT = 5.0
# What every open resets them to; `jv` and `si` are kept [10].
_PER_OPEN = {"ej": 1.0, "sv": 1.0, "qv": 0.0}


class Settings:
    """Values by key; numbers are floats, as on the board."""

    def __init__(self, config: SimConfig) -> None:
        self._config = config
        self._values: dict[str, float] = {
            "ej": 1.0,
            "jv": 2.0,  # JV_MESSAGES
            "js": 1.0,
            "sv": 1.0,
            "si": config.status_interval * 1000.0,
            "qv": 0.0,
            "sl": 1.0,
            "lim": 1.0,
            "saf": 1.0,
            "prbin": PROBING_INPUT,
        }
        for axis in AXES:
            self._values[f"{axis}vm"] = config.rapid_rate
            self._values[f"{axis}fr"] = config.rapid_rate
            self._values[f"{axis}tn"] = 0.0
            self._values[f"{axis}tm"] = float(config.travel.get(axis, 0.0))
        self.sr_keys: list[str] = list(reports.DEFAULT_SR)
        # What a status report, a GET, or the report list may name: the spindle's by build.
        self.report_keys = frozenset((*reports.SR_KEYS, *reports.spindle_keys(config.fb)))
        # The override factors and their enables, named as the build names them
        # (g2builds.py): factors 1.0; 100.26's enables off, 101.02+'s on.
        build = Build(config.fb)
        renamed = build.fb >= OVERRIDES_RENAMED
        self._override_keys = build.override_keys
        self._enables = (
            {"feed": "froe", "rapid": "troe", "spindle": "spoe"}
            if renamed
            else {"feed": "mfoe", "rapid": "mtoe", "spindle": "ssoe"}
        )
        for key in self._override_keys.values():
            self._values[key] = 1.0
        for key in self._enables.values():
            self._values[key] = 1.0 if renamed else 0.0
        # 101.02+: `froe`/`troe` are read-only, their table's setter is the getter.
        self._read_only: frozenset[str] = frozenset({"froe", "troe"} if renamed else ())

    def __getitem__(self, key: str) -> float:
        return self._values[key]

    def __contains__(self, key: str) -> bool:
        return key in self._values or key in self.identity

    def override(self, what: str) -> float:
        """The factor in force for "feed", "rapid" or "spindle": 1.0 while its enable is off
        (edge-preview plan_zoid.cpp:145-148)."""
        if not self._values[self._enables[what]]:
            return 1.0
        return self._values[self._override_keys[what]]

    def reset_overrides(self) -> None:
        """cm_reset_overrides at a program end: feed and traverse back to 1.0 (edge-preview
        canonical_machine.cpp:1436-1442; 100.26 also turns their enables off)."""
        for what in ("feed", "rapid"):
            self._values[self._override_keys[what]] = 1.0
            if self._enables[what] not in self._read_only:
                self._values[self._enables[what]] = 0.0

    def reset_per_open(self) -> None:
        self._values.update(_PER_OPEN)

    @property
    def identity(self) -> dict[str, Any]:
        """What the banner says about the board; read-only."""
        fb = self._config.fb
        return {
            "fv": FV,
            "fb": fb,
            "fbs": f"{fb:.2f}-sim",
            "fbc": "settings_sim.h",
            "hp": "sim",
            "hv": "sim",
            "id": BOARD_ID,
        }

    def get(self, key: str) -> Any:
        """The value of a known key (see `in`), as the board prints it."""
        if key in self.identity:
            return self.identity[key]
        return reports.number(self._values[key], 3)

    def system_group(self) -> dict[str, Any]:
        """`{sys:n}`, `$`: identity and communication settings in one object."""
        group = dict(self.identity)
        for key in ("ej", "jv", "js", "sv", "si", "qv"):
            group[key] = self.get(key)
        return group

    def set(self, key: str, value: Value) -> Status:
        """Store `value` under a known key, checked as the board checks it."""
        if key in self.identity:
            return Status.PARAMETER_IS_READ_ONLY
        if key in self._read_only:
            return Status.OK  # the setter is the getter: the answer shows the value kept
        if isinstance(value, bool):
            number = 1.0 if value else 0.0
        elif isinstance(value, float):
            number = value
        else:
            return Status.VALUE_TYPE_ERROR
        low, high = self._range(key)
        if low is not None and number < low:
            return Status.INPUT_LESS_THAN_MIN_VALUE
        if high is not None and number > high:
            return Status.INPUT_EXCEEDS_MAX_VALUE
        if key == "si":
            # g2core raises it to 100 ms; a faster configured interval stays allowed for tests.
            number = max(number, min(MIN_SI_MS, self._config.status_interval * 1000.0))
        self._values[key] = number
        return Status.OK

    def _range(self, key: str) -> tuple[float | None, float | None]:
        """What `set_float_range` and `set_01` accept for `key` (None: no bound)."""
        for what, factor_key in self._override_keys.items():
            if key == factor_key:
                low, high = OVERRIDE_RANGES[what]
                return low / 100.0, high / 100.0
            if key == self._enables[what]:
                return 0.0, 1.0
        low_, high_ = _RANGES.get(key, (None, None))
        return low_, high_

    def set_status_report(self, value: Value) -> Status:
        """`{sr:{posx:t,...}}` replaces the list: leaf keys, each true, 1 to 39 of them [4]."""
        if not isinstance(value, dict):
            return Status.UNSUPPORTED_TYPE
        keys: list[str] = []
        for key, flag in value.items():
            if key not in self.report_keys:
                return Status.UNRECOGNIZED_NAME
            if flag is not True:
                return Status.UNSUPPORTED_TYPE
            keys.append(key)
        if not keys:
            return Status.INPUT_LESS_THAN_MIN_VALUE
        if len(keys) > reports.MAX_SR_KEYS:
            return Status.INPUT_EXCEEDS_MAX_VALUE
        self.sr_keys = keys
        return Status.OK
