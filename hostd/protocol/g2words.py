"""g2core's words for what an operator asks: how a jog, a tool change, a homing, a zero,
an alarm or a shutdown, a setting, a probe's input and the work offsets are written on
g2core 100.x-101.x, and how the board's answers to the reads among them are read.

`G2Words` is a part of `G2Session` (g2core.py), which holds the rules of the wire: line
mode, holds, lockouts, kills and flushes, the handshake. These are the dialect's
vocabulary that SessionBase declares (see `jog_lines` there): functions of the board's
build and of what its reports said, so the machine layer never names a dialect.
Sources are synthetos/g2 files, cited as in g2core.py.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from typing import Any

from hostd.protocol.commands import InvalidCommand, Refusal
from hostd.protocol.g2builds import Build
from hostd.protocol.gcode import HOME_AXES, axes_words, jog_line
from hostd.protocol.gcodestate.resume import Board
from hostd.protocol.gcodestate.state import MM_PER_INCH
from hostd.protocol.limits import MachineLimits
from hostd.protocol.messages import JsonObject
from hostd.protocol.model import MachineModel
from hostd.protocol.probing import ProbeInput, number
from hostd.protocol.settings import set_lines
from hostd.protocol.status import message
from hostd.protocol.words import Words

_LIMIT_AXES = ("x", "y", "z")
_OFFSET_GROUPS = ("g54", "g55", "g56", "g57", "g58", "g59")


class G2Words(Words):
    """The operator's words on g2core, for `G2Session`."""

    # The session's: its machine's id, the board's build rules (from its `fb`) and what
    # its reports said (the units and the work coordinate system in force).
    id: str
    build: Build
    model: MachineModel

    report_line: str | None = "{sr:n}"  # a GET: answered once the report has been printed

    def position_scales(self) -> tuple[float, float]:
        """`mpo` is absolute and in mm whatever the units mode (canonical_machine.cpp:2066
        `cm_get_absolute_position`, `_f0`: no conversion); `pos` is in the units mode in
        force (:575-589 `cm_get_display_position` divides by 25.4 under G20)."""
        return 1.0, MM_PER_INCH if self.model.units == "in" else 1.0

    def spindle_max_setting(self) -> str | None:
        """`th2mxs`, the S of the laser toolhead's full power (edge-preview
        board/ArduinoDue/0_hardware.cpp:296; laser_toolhead.h:255 scales S between
        `th2mns` and it); absent before 101.05 and on builds without a laser toolhead,
        which then refuse it. `laser_test` is refused on g2core anyway: the toolhead
        fires by distance moved (laser_toolhead.h:491-515), never standing still."""
        return "th2mxs" if self.build.fb >= 101.05 else None

    def jog_lines(self, axes: Mapping[str, float], feed: float) -> list[str]:
        """A relative move, then G90 back: a jog is G-code on g2core."""
        return [jog_line(axes, feed), "G90"]

    def tool_change_line(self, text: str, tool: int | None) -> str:
        """The line as written: g2core takes M6 (gcode_parser.cpp `case 6`, tool_change)
        and only makes the selected tool the current one (canonical_machine.cpp
        `_exec_change_tool`), so its `tool` reports the change."""
        return text

    def tool_length_lines(self, tool: int, delta: float) -> list[str]:
        """g2core has no G43.1 (gcode_parser.cpp `case 43`: only G43 and G43.2): the
        offset goes into the tool's entry of the tool table (G10 L1, cm_set_g10_data;
        entries from 1, TOOLS of them) and G43 H applies it (cm_set_tl_offset)."""
        entry = max(tool, 1)
        return [f"G10 L1 P{entry} Z{delta:.4f}", f"G43 H{entry}"]

    def home_lines(self, axes: Sequence[str] | None) -> list[str]:
        """`G28.2` with a word per axis: cycle_homing.cpp homes the axes named.

        g2core answers it as the cycle starts (cm_homing_cycle_start sets
        MACHINE_CYCLE / CYCLE_HOMING at once: the combined state reads HOMING);
        the cycle's end is the state leaving HOMING.
        """
        return [f"G28.2 {axes_words(axes or HOME_AXES)}"]

    def homing_failed(self, report: Mapping[str, Any]) -> bool:
        """g2core's homing failures are statuses 240-247 (error.h STAT_HOMING_*)."""
        status = report.get("st")
        return isinstance(status, int) and 240 <= status <= 247

    def status_text(self, code: int) -> str:
        return message(code)  # status.py: g2core's own table (error.h)

    def alarm_line(self) -> str:
        return "{alarm:n}"  # config_app.cpp: a GET that raises the alarm

    def shutdown_line(self) -> str:
        return "{shutd:n}"

    def probe_input_reads(self) -> list[str]:
        """`{"prbin":null}`: the digital input G38.x reads (canonical_machine.cpp
        `prb_config_items_1`, cm_get_probe_input)."""
        return [json.dumps({"prbin": None})]

    def probe_input(self, bodies: list[JsonObject]) -> ProbeInput:
        """`in<prbin>` (config_app.cpp's `in1`..: din_get_input), read by a GET.

        prbin 0 is no input: gpio_read_input(0) reads false (gpio.cpp), so a G38.2
        could never trip and ends in an alarm at the end of its travel.
        """
        n = next((b["prbin"] for b in bodies if "prbin" in b), None)
        if not isinstance(n, int | float) or isinstance(n, bool) or int(n) < 1:
            raise InvalidCommand(
                Refusal.UNREADABLE,
                f"{self.id} has no probe input configured (prbin is {n}): set prbin to the"
                " digital input the plate is wired to",
            )
        key = f"in{int(n)}"
        return ProbeInput(key, json.dumps({key: None}))

    def work_zero_line(self, values: Mapping[str, float]) -> str:
        """P1..P6 for G54..G59: cm_set_g10_data refuses P0 (STAT_P_WORD_IS_INVALID,
        canonical_machine.cpp), so the active WCS must be known from `coor`."""
        wcs = self.model.modal.get("wcs")
        p = _OFFSET_GROUPS.index(wcs.lower()) + 1 if wcs and wcs.lower() in _OFFSET_GROUPS else 0
        if not p:
            raise InvalidCommand(
                Refusal.UNREADABLE,
                f"the active work coordinate system is {wcs or 'unknown'}: select G54-G59 first",
            )
        words = " ".join(f"{a.upper()}{number(v)}" for a, v in values.items())
        return f"G10 L20 P{p} {words}"

    def settings_read(self, keys: list[str]) -> list[str]:
        return [json.dumps({key: None}) for key in keys]

    def settings_write(self, values: Mapping[str, bool | int | float | str]) -> list[str]:
        return set_lines(values)  # the board answers each with the value it stored

    def settings_found(self, keys: list[str], bodies: list[JsonObject]) -> dict[str, Any]:
        merged: dict[str, Any] = {}
        for body in bodies:
            merged.update(body)
        return merged

    def limit_settings(self) -> list[str]:
        return [f"{a}{k}" for a in _LIMIT_AXES for k in ("tn", "tm", "vm")]

    def machine_limits(self, found: Mapping[str, Any]) -> MachineLimits:
        """Travel from `xtn`..`xtm`, traverse velocity `xvm`; g2core plans by jerk (`xjm`),
        not acceleration, so none is given."""
        travel: dict[str, tuple[float, float]] = {}
        velocity: dict[str, float] = {}
        for a in _LIMIT_AXES:
            low, high, vm = (setting_number(found.get(f"{a}{k}")) for k in ("tn", "tm", "vm"))
            if low is not None and high is not None and high > low:
                travel[a] = (low, high)
            if vm:
                velocity[a] = vm
        return MachineLimits(travel, velocity)

    def offset_reads(self) -> list[str]:
        """`{"g54":null}` .. `{"g59":null}` and `{"g92":null}`: groups of per-axis values
        (config_app.cpp, `g54x`..; G10 writes them and g2core persists them), and
        `{"g92e":null}`: program end only suspends G92 (its values stay, not in force)."""
        return [json.dumps({group: None}) for group in (*_OFFSET_GROUPS, "g92", "g92e")]

    def board_offsets(self, bodies: list[JsonObject]) -> Board:
        """The groups' values, converted from the units the board reports in (F_CONVERT:
        the units in force, as the status report's `unit`) to mm."""
        scale = 25.4 if self.model.units == "in" else 1.0
        found: dict[str, dict[str, float]] = {}
        for body in bodies:
            for group, values in body.items():
                if isinstance(values, dict):
                    found[group] = {
                        a: float(v) * scale
                        for a, v in values.items()
                        if a in ("x", "y", "z") and isinstance(v, int | float)
                    }
        offsets = {f"G{g[1:]}": found[g] for g in _OFFSET_GROUPS if g in found}
        enabled = next((body["g92e"] for body in bodies if "g92e" in body), 1)
        return Board(offsets, found.get("g92", {}) if enabled else {})


def setting_number(value: object) -> float | None:
    """A number the board answered (a setting, its `fb`), or None for anything else."""
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None
