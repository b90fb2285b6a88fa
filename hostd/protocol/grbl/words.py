"""grbl's words for what an operator asks: how a jog, a tool change, a homing, a zero,
a setting, a probe's input or a laser test is written on grbl 1.1 and grblHAL, and how
the board's answers to the reads among them (`$$`, `$#`, `$G`) are read.

`GrblWords` is a part of `GrblSession` (session.py), which holds the rules of the
wire: flow control, holds, lockouts, resets. These are the dialect's vocabulary
that SessionBase declares (see `jog_lines` there): pure functions of the board's
build and of the settings its handshake read, so the machine layer never names a
dialect. Sources are cited as in session.py.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from hostd.protocol.commands import InvalidCommand, Refusal
from hostd.protocol.gcode import HOME_AXES, WCS_P, jog_words, work_zero_line
from hostd.protocol.gcodestate.resume import Board
from hostd.protocol.grbl import codec
from hostd.protocol.grbl.codes import error_text
from hostd.protocol.limits import MachineLimits
from hostd.protocol.messages import JsonObject
from hostd.protocol.model import MachineModel
from hostd.protocol.numbers import format_setting
from hostd.protocol.probing import ProbeInput, number
from hostd.protocol.toolchange import without_m6
from hostd.protocol.words import Words, gcode_number

_RATE, _ACCEL, _TRAVEL = (110, 111, 112), (120, 121, 122), (130, 131, 132)  # $N, X Y Z
_OFFSET_KINDS = frozenset({"G54", "G55", "G56", "G57", "G58", "G59", "G92"})
_HOMING, _HOMING_DIR = 22, 23  # the homing cycle's flags, the axes that home to their low end
_FORCE_SET_ORIGIN = 1 << 3  # grblHAL's `$22` "Set machine origin to 0"


def _mask(value: object) -> int:
    """A bit-mask setting as a number read it (`$22=9`, 9.0); 0 when absent or not one."""
    if isinstance(value, float | int) and math.isfinite(value) and value == int(value) >= 0:
        return int(value)
    return 0


# mm/min (or in/min under G20): the feed a laser test's G1 defines on a board with none.
# It moves nothing; it stays the modal feed, so slow, for a program that never sets one.
LASER_TEST_FEED = 100.0


class GrblWords(Words):
    """The operator's words on grbl, for `GrblSession`."""

    # What the session's handshake read: the receive buffer (`[OPT:]`) and `$$`.
    rx_size: int
    settings: dict[str, str]
    model: MachineModel  # the session's

    # grbl answers `$H` only once the cycle has ended (system.c); the session sets
    # `homed` from that answer.
    homing_answered_at_end = True

    # `?` written as a client's line is answered by the next report (`GrblSession.send`):
    # one asked after a line's `ok` is printed after that line ran, so its position has
    # the line in it (a G10's new offset: both grbls put WCO in the report after one,
    # gnea/grbl gcode.c `system_flag_wco_change`, grblHAL the same).
    report_line = "?"

    # No alarm_line or shutdown_line: neither grbl 1.1 (system.c system_execute_line)
    # nor grblHAL (system.c sys_commands) has a command that raises an alarm, and
    # `$SLP` is a maintenance command (maintenance.py), so SessionBase refuses both.

    def jog_lines(self, axes: Mapping[str, float], feed: float) -> list[str]:
        """`$J=G91 X1.5000 F600.000`: grbl allows no G1 in a jog (gcode.c), and 0x85 cancels it."""
        return [f"$J=G91 {jog_words(axes, feed)}"]

    def tool_change_line(self, text: str, tool: int | None) -> str:
        """Without its M6: grbl refuses it (gnea/grbl gcode.c, `default:
        FAIL(STATUS_GCODE_UNSUPPORTED_COMMAND)` in the M switch: error:20), and grblHAL's
        own tool-change cycle must not run behind the host's. The T word stays (gcode.c
        only tracks it); a line of M6 alone becomes `T<tool>`."""
        return without_m6(text) or f"T{tool or 0}"

    def tool_length_lines(self, tool: int, delta: float) -> list[str]:
        """G43.1, grbl's dynamic tool length offset (gcode.c `case 43`, mantissa 10)."""
        return [f"G43.1 Z{delta:.4f}"]

    def spindle_max_setting(self) -> str | None:
        """`$30`, the S of full power (gnea/grbl settings.c; laser PWM is S / $30)."""
        return "30"

    def beam_on_line(self, speed: float) -> str:
        """`M4`: in laser mode, dynamic power, and none at rest (gnea/grbl
        spindle_control.c:252-253 gives M4 zero power whenever it is synced standing
        still), so the beam burns only along the frame's moves."""
        return f"M4 S{gcode_number(speed)}"

    def laser_test_reads(self) -> list[str]:
        """`$G`: its `[GC:]` says the modal feed `laser_test_lines` needs."""
        return ["$G"]

    def laser_test_lines(self, speed: float, seconds: float) -> list[str]:
        """`G1 M3 S..`, `G4 P..`, `M5`: in laser mode grbl lights M3 standing still only
        when the motion mode is G1/G2/G3 (gnea/grbl gcode.c:868-893: any other motion
        mode sets GC_PARSER_LASER_DISABLE and the sync passes zero power, :917-938;
        a G1 with no axis word moves nothing, :875-879), and keeps it through the dwell
        (mc_dwell only waits); `M5` turns it off (spindle_sync, :945). The motion mode
        is left at G1.

        A G1 needs a feed defined even when it moves nothing (gcode.c:167 and :664:
        error:22, as a board fresh from a reset has none): where `$G` said none, the
        G1 gives `LASER_TEST_FEED`, a slow one, which stays the modal feed. A board
        that has a feed keeps its own."""
        feed = self.model.feed
        f = "" if feed is not None and feed > 0 else f" F{gcode_number(LASER_TEST_FEED)}"
        return [f"G1{f} M3 S{gcode_number(speed)}", f"G4 P{gcode_number(seconds)}", "M5"]

    def line_limit(self) -> int:
        """The receive buffer less one (`[OPT:]`'s, or classic grbl's 128)."""
        return self.rx_size - 1

    def position_scales(self) -> tuple[float, float]:
        """`MPos` and `WPos` are in mm, or both in inches with `$13=1`, whatever G20 or
        G21 is in force (gnea/grbl report.c `report_util_axis_values`; grblHAL the same)."""
        found = codec.numbers(self.settings.get("13", ""))
        scale = 25.4 if found == [1.0] else 1.0
        return scale, scale

    def known_travel(self) -> dict[str, tuple[float, float]]:
        """The travel of `$130`.. as the handshake's `$$` read them."""
        found: dict[str, Any] = {}
        for key in self.limit_settings():
            try:
                found[key] = float(self.settings[key])
            except (KeyError, ValueError):
                continue
        return dict(self.machine_limits(found).travel)

    def home_lines(self, axes: Sequence[str] | None) -> list[str]:
        """`$H`: every axis the board's `$23`.. homes. One-axis `$HX` needs grblHAL's
        single-axis homing setting (system.c go_home): refused here, not guessed."""
        if axes is not None and set(axes) != set(HOME_AXES):
            raise InvalidCommand(
                Refusal.UNREADABLE,
                "grbl homes every axis at once with $H: leave axes out (or give x, y and z)",
            )
        return ["$H"]

    def zero_line(self, wcs: str | None, axes: Mapping[str, float]) -> str:
        """As every dialect's, but an unknown WCS is `P0`: gnea/grbl gcode.c reads G10 P0
        as the active coordinate system."""
        return work_zero_line(WCS_P.get(wcs or "", 0), axes)

    def status_text(self, code: int) -> str:
        return error_text(code)  # codes.py: grblHAL errors.c (classic grbl: 1-38)

    def probe_input_reads(self) -> list[str]:
        return []  # every status report shows it

    def probe_input(self, bodies: list[JsonObject]) -> ProbeInput:
        """`Pn:P` in every status report while the probe pin reads closed (gnea/grbl
        report.c report_realtime_status: probe_get_state(); grblHAL report.c the same),
        read into the report's `pin_p` (report.py)."""
        return ProbeInput("pin_p")

    def work_zero_line(self, values: Mapping[str, float]) -> str:
        """`G10 L20 P0`: P0 is the active coordinate system (gnea/grbl gcode.c, "Index P0
        as the active coordinate system"), so no report of it is needed."""
        words = " ".join(f"{a.upper()}{number(v)}" for a, v in values.items())
        return f"G10 L20 P0 {words}"

    def settings_read(self, keys: list[str]) -> list[str]:
        _setting_numbers(keys)
        return ["$$"]  # one line lists them all

    def settings_write(self, values: Mapping[str, bool | int | float | str]) -> list[str]:
        _setting_numbers(list(values))
        lines = []
        for key, value in values.items():
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise InvalidCommand(Refusal.BAD_VALUE, f"grbl setting ${key} takes a number")
            lines.append(f"${key}={format_setting(value, f'grbl setting ${key}')}")
        return lines

    def settings_found(self, keys: list[str], bodies: list[JsonObject]) -> dict[str, Any]:
        """`$N=V` lines of `$$`, by number; a setting the board has not is absent."""
        found: dict[str, Any] = {}
        for body in bodies:
            for line in body.get("lines", ()):
                key, _, value = str(line).removeprefix("$").partition("=")
                if key in keys:
                    numbers = codec.numbers(value)
                    found[key] = numbers[0] if numbers and len(numbers) == 1 else value
        return found

    def limit_settings(self) -> list[str]:
        return [str(n) for n in (*_RATE, *_ACCEL, *_TRAVEL, _HOMING, _HOMING_DIR)]

    def machine_limits(self, found: Mapping[str, Any]) -> MachineLimits:
        """`$110`.. max rate, `$120`.. acceleration, `$130`.. max travel.

        grbl's machine coordinates run from -max travel to 0 (gnea/grbl limits.c:376-383
        without HOMING_FORCE_SET_ORIGIN, a build option no setting shows). grblHAL's
        `$22` bit 3, "Set machine origin to 0" (core settings.h `force_set_origin`),
        puts 0 where the axis homes: an axis homing to its low end (`$23` bit set) then
        runs from 0 to +max travel (machine_limits.c:116-139 `limits_set_work_envelope`,
        settings.c:254: max travel is kept negative). Classic grbl's `$22` is 0 or 1."""
        travel: dict[str, tuple[float, float]] = {}
        velocity: dict[str, float] = {}
        accel: dict[str, float] = {}
        homing, dirs = (_mask(found.get(str(n))) for n in (_HOMING, _HOMING_DIR))
        origin_at_home = bool(homing & _FORCE_SET_ORIGIN)
        for i, axis in enumerate(("x", "y", "z")):
            rate, acc, span = (found.get(str(n[i])) for n in (_RATE, _ACCEL, _TRAVEL))
            if isinstance(rate, float | int) and rate > 0:
                velocity[axis] = float(rate)
            if isinstance(acc, float | int) and acc > 0:
                accel[axis] = float(acc)
            if isinstance(span, float | int) and span > 0:
                low_end = origin_at_home and bool(dirs & (1 << i))
                travel[axis] = (0.0, float(span)) if low_end else (-float(span), 0.0)
        return MachineLimits(travel, velocity, accel)

    def offset_reads(self) -> list[str]:
        """`$#` (report_ngc_parameters: `[G54:x,y,z]`.. `[G92:..]`, report.c) and `$G`
        (`[GC:...]`, whose S is the speed M3 would run at)."""
        return ["$#", "$G"]

    def board_offsets(self, bodies: list[JsonObject]) -> Board:
        """In mm: `$#` reports in inches only with `$13=1`, as the positions do
        (report_util_axis_values: `position_scales`)."""
        scale, _ = self.position_scales()
        offsets: dict[str, dict[str, float]] = {}
        g92: dict[str, float] = {}
        speed: float | None = None
        for body in bodies:
            for text in body.get("lines", ()):
                kind, _, values = str(text).strip("[]").partition(":")
                if kind == "GC":
                    for word in values.split():
                        if word.startswith("S") and codec.numbers(word[1:]):
                            speed = float(word[1:])
                    continue
                numbers = codec.numbers(values)
                if numbers is None or kind not in _OFFSET_KINDS:
                    continue
                axes = dict(zip(("x", "y", "z"), (n * scale for n in numbers), strict=False))
                if kind == "G92":
                    g92 = axes
                else:
                    offsets[kind] = axes
        return Board(offsets, g92, speed)


def _setting_numbers(keys: list[str]) -> None:
    """grbl's settings are numbered (`$110`): a key is the number."""
    for key in keys:
        if not key.isdigit():
            raise InvalidCommand(
                Refusal.RESERVED_KEY,
                f"{key!r} is not a grbl setting: name it by its number, as 110",
            )


def homing_time_bound(settings: Mapping[str, str]) -> float | None:
    """The longest a homing cycle can take, in seconds, from the board's `$$`; None if unknown.

    grbl 1.1's limits_go_home (limits.c) and grblHAL's (machine_limits.c) home
    each cycle alike: a search of 1.5 x the longest travel (`$130`..) at the seek
    rate (`$25`), then for each locate cycle (grblHAL `$43`, grbl 1) a pull-off of
    `$27` at the seek rate and an approach of 10 x `$27` (grblHAL's
    HOMING_AXIS_LOCATE_SCALAR; grbl's is 5) at the feed rate (`$24`), and a last
    pull-off; after each move a debounce delay of `$26` ms. Which axes home
    together is a build option the host cannot read, so every axis is taken as a
    cycle of its own (the longest case); each move also accelerates to its rate
    and back (`$120`..). 1.5 times that covers a slow start and a report's delay.
    """

    def number(key: int) -> float | None:
        found = codec.numbers(settings.get(str(key), ""))
        ok = found is not None and len(found) == 1 and math.isfinite(found[0])
        return found[0] if found and ok else None

    seek, feed = number(25), number(24)
    if seek is None or feed is None or seek <= 0 or feed <= 0:
        return None
    pulloff = max(number(27) or 0.0, 0.0)
    debounce = max(number(26) or 0.0, 0.0) / 1000
    locates = min(max(int(number(43) or 1), 1), 128)  # grblHAL takes 1..128
    total = 0.0
    for axis in range(6):
        travel = number(130 + axis)
        if travel is None or travel <= 0:
            continue
        moves = [(1.5 * travel, seek)]
        moves += [(pulloff, seek), (10 * pulloff, feed)] * locates + [(pulloff, seek)]
        accel = number(120 + axis)
        for distance, rate in moves:
            speed = rate / 60  # mm/s
            total += distance / speed + debounce
            if accel is not None and accel > 0:
                total += speed / accel
    return 1.5 * total if total > 0 else None
