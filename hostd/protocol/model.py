"""The machine model: what the daemon knows of one controller, updated from what it says.

Pure: status reports, requested reports and exception reports go in,
`snapshot()` (the api.md machine snapshot, less the parts owned by the
supervisor, the faults and the jobs) comes out.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from hostd.protocol.messages import ExceptionReport, JsonObject
from hostd.protocol.states import MachineState, state_from_code
from hostd.protocol.status import Status

AXES = ("x", "y", "z", "a", "b", "c")
_UNITS = {0: "in", 1: "mm"}
# g2core's enums as the G-code word that sets each (canonical_machine.h: coor,
# dist, frmo, momo), so a client reads "G55", not 2.
_WCS = {0: "G53", 1: "G54", 2: "G55", 3: "G56", 4: "G57", 5: "G58", 6: "G59"}
_DISTANCE = {0: "G90", 1: "G91"}
_FEED_MODE = {0: "G93", 1: "G94", 2: "G95"}
_MOTION = {0: "G0", 1: "G1", 2: "G2", 3: "G3", 4: "G80"}
# Status report keys read as one of the codes above.
_MODAL = {"coor": ("wcs", _WCS), "dist": ("distance", _DISTANCE)}
_MODAL |= {"frmo": ("feed_mode", _FEED_MODE), "momo": ("motion", _MOTION)}
# A limit switch unhomes the machine (seed 000); so does SHUTDOWN.
_UNHOMING_STATUS = frozenset({Status.LIMIT_SWITCH_HIT})
# g2core's spindle keys (g2handshake.py SPINDLE_KEYS). `spc`: 0 off, 1 CW, 2 CCW, 3 paused
# in a hold (101.03 spindle.h:49-53). 100.26's `spe` (0 off, 1 on, 2 paused) with `spd`
# (0 CW, 1 CCW; spindle.h:37-46). A paused spindle is stopped: "off" until the hold ends.
_SPINDLE_STATE = {0: "off", 1: "cw", 2: "ccw", 3: "off"}
_SPINDLE_ENABLED = {0: "off", 2: "off"}
_SPINDLE_DIRECTION = {0: "cw", 1: "ccw"}
_SPINDLE_KEYS = frozenset({"spc", "sps", "spe", "spd"})


@dataclass(slots=True)
class MachineModel:
    id: str
    state: MachineState | None = None
    position: dict[str, float] = field(default_factory=dict)
    line: int | None = None
    velocity: float | None = None
    feed: float | None = None
    units: str | None = None
    homed: bool | None = None
    machine_position: dict[str, float] = field(default_factory=dict)
    modal: dict[str, str | None] = field(default_factory=dict)  # wcs, distance, ...
    hold: int | None = None
    tool: int | None = None
    probe: dict[str, Any] | None = None  # the last probe cycle's result
    last_exception: JsonObject | None = None
    # What only some dialects report: the board's own state text (grbl: "Hold:0",
    # "Door:1", "Check") and laser mode (grbl's $32).
    board_state: str | None = None
    laser_mode: bool | None = None
    overrides: dict[str, float] | None = None  # percent: feed, rapid, spindle (grbl's Ov)
    reports: int = 0  # status reports taken: one newer than a request is that request's
    override_reports: int = 0  # how many reports carried the overrides: a fresh one is news
    # The spindle as the board reports it: {"state": "cw"|"ccw"|"off", "speed"}; None unknown.
    spindle: dict[str, Any] | None = None
    spindle_words: dict[str, int] = field(default_factory=dict)  # 100.26's `spe` and `spd`
    # grbl's `$N` blocks: [{"n", "line", "acts"}], `acts` what it does at a reset (or None).
    startup_blocks: list[dict[str, Any]] | None = None

    def apply_status(self, fields: JsonObject) -> MachineState | None:
        """Take one status report (automatic or requested); return the new state if it changed."""
        before = self.state
        self.reports += 1
        for key, value in fields.items():
            if key == "stat":
                self.state = state_from_code(value) or self.state
            elif key.startswith("pos") and key[3:] in AXES and _is_number(value):
                self.position[key[3:]] = float(value)
            elif key == "line" and _is_number(value):
                self.line = int(value)
            elif key == "vel" and _is_number(value):
                self.velocity = float(value)
            elif key == "feed" and _is_number(value):
                self.feed = float(value)
            elif key == "unit":
                self.units = _UNITS.get(value, self.units) if _is_number(value) else self.units
            elif key == "home" and _is_number(value):
                self.homed = bool(value)
            elif key.startswith("mpo") and key[3:] in AXES and _is_number(value):
                self.machine_position[key[3:]] = float(value)
            elif key in _MODAL:
                name, codes = _MODAL[key]
                self.modal[name] = codes.get(int(value)) if _is_number(value) else None
            elif key == "hold" and _is_number(value):
                self.hold = int(value)
            elif key == "tool" and _is_number(value):
                self.tool = int(value)
            elif key in _SPINDLE_KEYS and _is_number(value):
                self._spindle_field(key, float(value))
        if self.state is MachineState.SHUTDOWN:
            self.homed = False
        return self.state if self.state is not before else None

    def _spindle_field(self, key: str, value: float) -> None:
        """g2core's `sps` (speed) and `spc`, or 100.26's `spe` and `spd` (see _SPINDLE_STATE)."""
        now = dict(self.spindle or {"state": None, "speed": None})
        if key == "sps":
            now["speed"] = value
        elif key == "spc":
            now["state"] = _SPINDLE_STATE.get(int(value), now["state"])
        else:
            words = self.spindle_words
            words[key] = int(value)
            enable, direction = words.get("spe"), words.get("spd")
            if enable in _SPINDLE_ENABLED:
                now["state"] = _SPINDLE_ENABLED[enable]
            elif enable == 1 and direction in _SPINDLE_DIRECTION:
                now["state"] = _SPINDLE_DIRECTION[direction]
        self.spindle = now

    def apply_exception(self, report: ExceptionReport) -> None:
        self.last_exception = report.fields
        if report.status in _UNHOMING_STATUS:
            self.homed = False

    def apply_probe(self, report: JsonObject) -> dict[str, Any]:
        """`{"prb":{"e":1,"x":..}}`: e is 1 when the probe made contact, 0 when it did not."""
        position = {a: float(v) for a, v in report.items() if a in AXES and _is_number(v)}
        self.probe = {"ok": report.get("e") == 1, "position": position}
        return self.probe

    def last_exception_message(self) -> str | None:
        msg = (self.last_exception or {}).get("msg")
        return msg if isinstance(msg, str) and msg else None

    def reset(self) -> None:
        """Forget everything the controller said: it rebooted or went away."""
        self.state = None
        self.position.clear()
        self.line = self.velocity = self.feed = None
        self.units = None
        self.homed = None
        self.machine_position.clear()
        self.modal.clear()
        self.hold = self.tool = None
        self.probe = None
        self.board_state = None
        self.laser_mode = None
        self.overrides = None
        self.spindle = None
        self.spindle_words.clear()
        self.startup_blocks = None

    def snapshot(self) -> dict[str, Any]:
        state = self.state
        return {
            "id": self.id,
            "state": None if state is None else {"code": int(state), "name": state.name},
            "position": dict(self.position),
            "line": self.line,
            "velocity": self.velocity,
            "feed": self.feed,
            "units": self.units,
            "homed": self.homed,
            "work_position": dict(self.position),
            "machine_position": dict(self.machine_position),
            "wcs": self.modal.get("wcs"),
            "distance": self.modal.get("distance"),
            "feed_mode": self.modal.get("feed_mode"),
            "motion": self.modal.get("motion"),
            "hold": self.hold,
            "tool": self.tool,
            "probe": self.probe,
            "last_exception": self.last_exception,
            "board_state": self.board_state,
            "laser_mode": self.laser_mode,
            "overrides": None if self.overrides is None else dict(self.overrides),
            "spindle": None if self.spindle is None else dict(self.spindle),
            "startup_blocks": self.startup_blocks,
        }


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)
