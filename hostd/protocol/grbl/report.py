"""grbl's reports under the common names model.py reads (g2core's: `stat`, `posx`, `mpox`, ...).

The status report (report.c `report_realtime_status`: `<Idle|MPos:...|FS:...>`),
the parser's modes (`[GC:...]`) and a probe's result (`[PRB:...]`); the
session (session.py) applies what this makes of them.
"""

from __future__ import annotations

import math
import re
from typing import Any

from hostd.protocol.grbl import codec
from hostd.protocol.grbl.codes import ALARM_STATE
from hostd.protocol.model import MachineModel
from hostd.protocol.states import MachineState

# The board's state name -> the common state (report.c `report_realtime_status`).
STATES: dict[str, MachineState] = {
    "Idle": MachineState.READY,
    "Run": MachineState.RUN,
    "Hold": MachineState.HOLD,
    "Jog": MachineState.JOG,
    "Home": MachineState.HOMING,
    "Alarm": MachineState.ALARM,
    "Check": MachineState.READY,  # check mode: lines are parsed, nothing moves
    "Door": MachineState.INTERLOCK,
    "Sleep": MachineState.SHUTDOWN,  # left only by a reset
    "Tool": MachineState.HOLD,  # a tool change waits for cycle start
}
_AXES = "xyzabc"
_PINS = {c: f"pin_{c.lower()}" for c in "XYZABCPDHRSE"}


class ReportReader:
    """Reads status reports, keeping what grbl sends only now and then (`WCO:`)."""

    def __init__(self) -> None:
        self.wco: list[float] | None = None  # work coordinate offset, sent now and then
        # Bf: free planner blocks, from the last report. report.c prints Bf in every
        # report while `$10` asks for it, so a report without it means unknown.
        self.planner_free: int | None = None

    def fields(self, report: codec.StatusReport, model: MachineModel) -> dict[str, Any]:
        """A report's fields under the common names (model.py reads them)."""
        state = STATES.get(report.state)
        if report.state == "Alarm" and report.sub is not None:
            state = ALARM_STATE.get(report.sub, MachineState.ALARM)
        elif report.state == "Alarm" and model.state is MachineState.SHUTDOWN:
            state = MachineState.SHUTDOWN  # an e-stop's alarm reads "Alarm" on classic grbl
        fields: dict[str, Any] = {} if state is None else {"stat": int(state)}
        raw = report.fields
        if "WCO" in raw:
            self.wco = codec.numbers(raw["WCO"])
        mpos = codec.numbers(raw["MPos"]) if "MPos" in raw else None
        wpos = codec.numbers(raw["WPos"]) if "WPos" in raw else None
        wco = self.wco
        if mpos is not None and wco is not None and len(wco) == len(mpos):
            wpos = [m - o for m, o in zip(mpos, wco, strict=True)]
        elif wpos is not None and wco is not None and len(wco) == len(wpos):
            mpos = [w + o for w, o in zip(wpos, wco, strict=True)]
        for prefix, values in (("mpo", mpos), ("pos", wpos)):
            for axis, value in zip(_AXES, values or (), strict=False):
                fields[f"{prefix}{axis}"] = value
        speeds = codec.numbers(raw.get("FS") or raw.get("F") or "")
        if speeds:
            fields["vel"] = speeds[0]
        if "Ln" in raw and raw["Ln"].isdigit():
            fields["line"] = int(raw["Ln"])
        bf = codec.numbers(raw["Bf"]) if "Bf" in raw else None
        self.planner_free = int(bf[0]) if bf else None
        if "H" in raw:
            fields["home"] = 1 if raw["H"].startswith("1") else 0
        if report.state == "Hold" and report.sub is not None:
            fields["hold"] = report.sub
        for key in ("Ov", "A"):
            if key in raw:
                fields[key.lower()] = raw[key]
        ov = codec.numbers(raw["Ov"]) if "Ov" in raw else None
        refresh = False  # an `Ov:` refresh, sent now and then (report.c's counters)
        if ov is not None and len(ov) == 3:
            model.overrides = dict(zip(("feed", "rapid", "spindle"), ov, strict=True))
            model.override_reports += 1
            refresh = True
        if refresh or "A" in raw:
            # `A:` is every accessory's state whenever it comes (S spindle CW, C CCW).
            # Classic grbl sends it only with Ov, and leaves it out when none is on
            # (gnea/grbl report.c:620-640). grblHAL also sends it alone, on the report
            # after the spindle, coolant or tool changes (core report.c:1475-1505,
            # spindle_control.c:750 `report_add_realtime(Report_Spindle)`), and leaves it
            # out of an Ov report while the spindle is off (report.c:1419).
            turning = _spindle_state(raw.get("A", ""))
            model.spindle = {"state": turning, "speed": (model.spindle or {}).get("speed")}
        if (
            speeds is not None and len(speeds) >= 2
        ):  # FS:feed,speed: the speed the spindle runs at now
            model.spindle = {"state": (model.spindle or {}).get("state"), "speed": speeds[1]}
        # Pins as keys a signal can name: pin_x .. pin_d (door), pin_p (probe), pin_e
        # (e-stop). grbl leaves Pn out when no pin is active, so every key is always set.
        active = raw.get("Pn", "")
        fields |= {key: int(letter in active) for letter, key in _PINS.items()}
        return fields


def _spindle_state(accessories: str) -> str:
    return "cw" if "S" in accessories else "ccw" if "C" in accessories else "off"


_INTEGER = re.compile(r"[-+]?[0-9]+")


def grbl_named(report: codec.StatusReport) -> dict[str, Any]:
    """A report under grbl's own names: a client's `?` through `machine.send`.

    `fields` above is for the model; a client asked grbl, so it hears grbl.
    `state` is the state word with its substate (`Hold:0`, as the snapshot's
    `board_state`: report.c prints it first, unnamed); every other field keeps
    the name report.c prints (`MPos`, `WPos`, `WCO`, `FS`, `F`, `Bf`, `Ln`,
    `Ov`, `Pn`, `A`, grblHAL's `H`, ...). A value of finite numbers becomes a
    list of them (integers stay integers: `FS:500,0`), any other value stays
    the text the board sent (`Pn:XP`).
    """
    named: dict[str, Any] = {
        "state": report.state + ("" if report.sub is None else f":{report.sub}")
    }
    for key, text in report.fields.items():
        values = codec.numbers(text) if text else None
        if values is None or not all(math.isfinite(v) for v in values):
            named[key] = text
            continue
        parts = text.split(",")
        named[key] = [
            int(part) if _INTEGER.fullmatch(part.strip()) else value
            for part, value in zip(parts, values, strict=True)
        ]
    return named


# `[GC:...]`'s words by modal group (NIST RS274NGC 3.4; grblHAL report.c
# report_gcode_modes, gnea/grbl report.c report_gcode_modes). The words come in an
# order that differs by build: grblHAL adds G92, G7/G8, G66, G96/G97, G40,
# G43/G49, G98/G99 and G50/G51 (scaling, printed `G51:XY`) between them, so a word
# is placed by its group, never by where it stands. The groups the snapshot has no
# field for are named too, so that none of their words is taken for another's.
_MOTION = {"G0", "G1", "G2", "G3", "G5", "G5.1", "G33", "G33.1", "G73", "G76"} | {
    f"G{n}" for n in (*range(80, 90), "38.2", "38.3", "38.4", "38.5")
}
_GROUPS: dict[str, str] = (
    dict.fromkeys(_MOTION, "motion")
    | dict.fromkeys(("G54", "G55", "G56", "G57", "G58", "G59", "G59.1", "G59.2", "G59.3"), "wcs")
    | dict.fromkeys(("G90", "G91"), "distance")
    | dict.fromkeys(("G93", "G94", "G95"), "feed_mode")
    | dict.fromkeys(("G20", "G21"), "units")
    | dict.fromkeys(("G17", "G18", "G19"), "plane")
    | dict.fromkeys(("G50", "G51"), "scaling")
    | dict.fromkeys(("G43", "G43.1", "G43.2", "G49"), "tool_length")
    | dict.fromkeys(("G40", "G41", "G41.1", "G42", "G42.1"), "cutter_comp")
    | dict.fromkeys(("G7", "G8", "G92", "G96", "G97", "G98", "G99", "G66", "G67"), "other")
)
_KEPT = frozenset({"motion", "wcs", "distance", "feed_mode"})  # the snapshot's modal fields


def apply_modes(model: MachineModel, text: str) -> None:
    """`[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]`: the parser's modal state.

    A word is read by its modal group: grblHAL's `G50` (scaling off) once read as
    the coordinate system because it starts like `G54`. `G51:XY` is scaling on,
    with the axes it scales.
    """
    modal = model.modal
    for word in text.split():
        code = word.partition(":")[0]
        group = _GROUPS.get(code)
        if group == "units":
            model.units = "in" if code == "G20" else "mm"
        elif group in _KEPT:
            modal[group] = code
        elif group is None and len(word) > 1 and word[1:].isdigit() and word[0] == "T":
            model.tool = int(word[1:])
        elif group is None and word.startswith("F") and (feed := codec.numbers(word[1:])):
            model.feed = feed[0]


def probe_report(text: str) -> dict[str, Any]:
    """`[PRB:1.000,2.000,-3.250:1]`: where the probe stopped, and whether it touched."""
    where, _, touched = text.rpartition(":")
    values = codec.numbers(where) or []
    report: dict[str, Any] = {"e": 1 if touched == "1" else 0}
    report |= {axis: v for axis, v in zip(_AXES, values, strict=False)}
    return report
