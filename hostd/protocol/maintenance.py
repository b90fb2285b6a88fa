"""Maintenance commands: the lines that wipe, store, sleep or jog absurdly (issue 24, part 3).

`machine.send` is for the lines of a working day. A few controller commands
are maintenance, done on purpose or not at all, and this module names them,
per dialect, as the firmware reads them:

grbl 1.1 (gnea/grbl `system.c`, `system_execute_line`) and grblHAL
(grblHAL/core `system.c`):
- `$RST=$`, `$RST=#`, `$RST=*` (grblHAL also `$RST=&`): restore the
  settings, the coordinate offsets, or everything, to the build's defaults;
  grbl resets itself after it (`mc_reset`).
- `$N0=...`, `$N1=...`: store a startup block, which the board runs after
  every reset and power-up (`system_execute_startup`), the resets hostd
  sends after a cancel included.
- `$I=...`: store the build info string.
- `$SLP`: the sleep state; only a reset leaves it.
- `$J=...` with a distance no machine travels (see `absurd_jog`).

grbl reads a line with its spaces dropped and its letters upper-cased
(`protocol.c`, `protocol_main_loop`), after comments are removed; so does
this module, so that `$ rst = *` is what it is.

g2core (synthetos/g2 `config_app.cpp`, the "Actions and Reports" rows):
`defa` (`set_defaults`, config.cpp: a true value restores the profile's
defaults, the daemon's link settings with them) and `flash` (`hw_flash`:
the bootloader). `validate_line` (commands.py) already refuses both on
every path, with `boot` (TinyG's name), so this module names them for the
record and for the same error.

`startup_block_acts` says what a grbl startup block does that a reset must
not do unasked: move (a motion word, or an axis word in the G0 the board
starts in), or start the spindle or laser (M3, M4) or coolant (M7, M8).

`grbl_powered` and `g2core_powered` say what a line a client sends would do
that a fault blocking a job forbids (machine.send, machine.maintenance): move
the machine, home it, or start its spindle or beam. Coolant is not among them:
turning it on makes nothing less safe.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from enum import StrEnum

from hostd.protocol.gcodewords import strip_comments
from hostd.protocol.relaxed import parse_relaxed

# A jog further than this (mm; degrees for A, B, C) is absurd when the travel is not
# known: 10 m is beyond the travel of any machine hostd drives on one axis.
SANE_JOG_MM = 10_000.0
MM_PER_INCH = 25.4

_BLANK = re.compile(r"\s+")
# grbl's store of a startup block, in a normalized line: `$N0=...` (system.c).
_STARTUP_STORE = re.compile(r"\$N\d+=")
# One word: a letter and the number-ish run after it. The two classes do not overlap,
# so a match never backtracks: linear in the line.
_WORD = re.compile(r"([A-Z])([^A-Z]*)")
_AXES = frozenset("XYZABCUVW")
# G codes that take axis words without moving to them (grbl gcode.c: the "axis command"
# of non-modal group 0 and G43.1; and g2core's G28.3, which sets the origin where the
# machine is, gcode_parser.cpp's NEXT_ACTION_SET_ABSOLUTE_ORIGIN).
_AXIS_NOT_MOTION = frozenset({"G10", "G28.1", "G28.3", "G30.1", "G92", "G43.1"})
# With g2core's homing cycles (G28.2, and G28.4 which sets no coordinates).
_MOTION = frozenset(
    {"G0", "G1", "G2", "G3", "G38.2", "G38.3", "G38.4", "G38.5", "G28", "G30", "G28.2", "G28.4"}
)
_STARTS = {"M3": "starts the spindle or laser", "M4": "starts the spindle or laser"}
_STARTS |= {"M7": "starts the coolant", "M8": "starts the coolant"}


class Kind(StrEnum):
    """What a maintenance command does; clients see it as `data.maintenance`."""

    RESTORE = "restore"  # settings, offsets or all back to defaults
    STARTUP_BLOCK = "startup-block"  # a block the board runs at every reset
    BUILD_INFO = "build-info"  # the board's stored build string
    SLEEP = "sleep"  # only a reset leaves it
    BOOTLOADER = "bootloader"  # g2core flash / boot
    ABSURD_JOG = "absurd-jog"  # a jog no machine's travel has room for


@dataclass(frozen=True, slots=True)
class Maintenance:
    kind: Kind
    why: str  # for the operator: what the command would do
    # Whether `machine.maintenance` may send it: an absurd jog never has a purpose, and
    # g2core's bootloader and defaults are refused on every path (commands.py).
    on_purpose: bool = True


def normalized(text: str) -> str:
    """The line as grbl reads it: comments removed, blanks dropped, letters upper-cased.

    Flat comments, an unclosed one to the end of the line, as protocol.c drops them, in
    linear time (gcodewords.strip_comments). Until 2026-11-29 this was a regex
    substitution of a comment that had to be closed, which took quadratic time on a
    line of `(`s: one `machine.send` of a 100,000-character line held a grbl
    machine's event loop for 2.6 s, and the socket takes lines of up to 1 MiB."""
    return _BLANK.sub("", strip_comments(text, "")[0]).upper()


def maintenance_command(
    dialect: str,
    text: str,
    *,
    travel: Mapping[str, tuple[float, float]] | None = None,
    inches: bool = False,
) -> Maintenance | None:
    """The maintenance command `text` is on this dialect's board, or None.

    `travel`: the machine's travel per axis (mm, machine coordinates) when known;
    `inches`: the board's modal units are G20 (a jog without G20/G21 is read in them).
    """
    if dialect == "grbl":
        return grbl_maintenance(text, travel or {}, inches)
    return g2core_maintenance(text, travel or {}, inches)


def grbl_maintenance(
    text: str, travel: Mapping[str, tuple[float, float]], inches: bool
) -> Maintenance | None:
    """grbl's (its registry entry's `maintenance`, dialects.py): as `maintenance_command`."""
    return _grbl(normalized(text), travel, inches)


def g2core_maintenance(
    text: str, travel: Mapping[str, tuple[float, float]], inches: bool
) -> Maintenance | None:
    """g2core's (its registry entry's `maintenance`): jogs are G-code there, none absurd here."""
    return _g2core(text)


def _grbl(line: str, travel: Mapping[str, tuple[float, float]], inches: bool) -> Maintenance | None:
    if line.startswith("$RST="):
        what = {"$": "settings", "#": "coordinate offsets", "*": "settings, offsets and startup"}
        return Maintenance(
            Kind.RESTORE,
            f"{line} restores the board's {what.get(line[5:], 'stored data')} to defaults",
        )
    if _STARTUP_STORE.match(line):
        return Maintenance(
            Kind.STARTUP_BLOCK,
            f"{line.partition('=')[0]}= stores a startup block, which the board runs at every "
            "reset and power-up",
        )
    if line.startswith("$I="):
        return Maintenance(Kind.BUILD_INFO, "$I= overwrites the board's stored build info")
    if line == "$SLP":
        return Maintenance(Kind.SLEEP, "$SLP puts the board to sleep: only a reset leaves it")
    if line.startswith("$J="):
        why = absurd_jog(line[3:], travel, inches=inches)
        if why is not None:
            return Maintenance(Kind.ABSURD_JOG, why, on_purpose=False)
    return None


def _g2core(text: str) -> Maintenance | None:
    """`{defa:1}`, `$defa=1`, `{flash:1}`: named for the record (validate_line refuses them)."""
    lowered = text.strip().lower()
    if not lowered.startswith(("{", "$")):
        return None  # G-code: a word in a comment is no command
    for key, kind, why in (
        ("defa", Kind.RESTORE, "defa restores the factory defaults, the link settings with them"),
        ("flash", Kind.BOOTLOADER, "flash starts the bootloader"),
        ("boot", Kind.BOOTLOADER, "boot starts the bootloader"),
    ):
        if re.search(rf"[{{$\s,\"']{key}\b", lowered):
            return Maintenance(kind, why, on_purpose=False)
    return None


def absurd_jog(
    words: str, travel: Mapping[str, tuple[float, float]], *, inches: bool = False
) -> str | None:
    """Why a `$J=` jog's words (normalized) are absurd, or None.

    Relative (G91) and work (G90) distances may not exceed the travel's span on
    that axis (no target inside the travel is further away than that from a
    point inside it); machine targets (G53) must lie inside the travel. Without
    a known travel the bound is SANE_JOG_MM. A number that is not finite, or
    that the host cannot read, is absurd too.
    """
    values: list[tuple[str, str]] = [(m[1], m[2]) for m in _WORD.finditer(words)]
    codes = {f"{letter}{_code(number)}" for letter, number in values if letter == "G"}
    scale = MM_PER_INCH if "G20" in codes or (inches and "G21" not in codes) else 1.0
    machine = "G53" in codes
    for letter, number in values:
        if letter not in _AXES:
            continue
        axis = letter.lower()
        try:
            value = float(number)
        except ValueError:
            return f"jog {letter}{number}: not a number the host can read"
        if not math.isfinite(value):
            return f"jog {letter}{number}: not a finite distance"
        mm = value * (scale if axis in "xyzuvw" else 1.0)
        if axis in travel:
            low, high = travel[axis]
            if machine and not low - 1e-6 <= mm <= high + 1e-6:
                return (
                    f"jog {letter}{number}: the target {mm:.3f} mm is outside the travel "
                    f"{low:.3f} to {high:.3f} mm"
                )
            if not machine and abs(mm) > high - low + 1e-6:
                return (
                    f"jog {letter}{number}: {abs(mm):.3f} mm is more than the axis travels "
                    f"({high - low:.3f} mm)"
                )
        elif abs(mm) > SANE_JOG_MM:
            return (
                f"jog {letter}{number}: more than {SANE_JOG_MM:g} mm, beyond any machine's travel"
            )
    return None


def _code(number: str) -> str:
    """`G01` is G1, `G0.0` is G0: the code as a table names it."""
    try:
        value = float(number)
    except ValueError:
        return number
    return f"{value:g}" if math.isfinite(value) else number


def startup_block_acts(block: str) -> str | None:
    """What a grbl startup block does at every reset that must not happen unasked, or None."""
    return _acts(normalized(block), _STARTS, ", G0 at reset")


def _acts(line: str, starts: Mapping[str, str], mode: str = "") -> str | None:
    """What a normalized G-code line does: moves the machine, or starts one of `starts`."""
    words = [(m[1], m[2]) for m in _WORD.finditer(line)]
    codes = {f"{letter}{_code(number)}" for letter, number in words if letter in "GM"}
    motion = sorted(codes & _MOTION)
    if motion:
        return f"moves the machine ({', '.join(motion)})"
    axes = [f"{letter}{number}" for letter, number in words if letter in _AXES]
    if axes and not codes & _AXIS_NOT_MOTION:
        return f"moves the machine ({' '.join(axes)} in the motion mode in force{mode})"
    for code, what in starts.items():
        if code in codes:
            return f"{what} ({code})"
    return None


# What a fault that blocks a job forbids a sent line to start (coolant is not refused).
_POWERS = {"M3": _STARTS["M3"], "M4": _STARTS["M4"]}


def grbl_powered(text: str) -> str | None:
    """What a line sent to a grbl board does that a fault blocking a job forbids, or None:
    a jog (`$J=`), a homing cycle (`$H`), a startup block that acts (grbl runs a block
    once as it stores it, system.c), or G-code that moves or starts the spindle."""
    line = normalized(text)
    if line.startswith("$J="):
        return "jogs the machine ($J=)"
    if line.startswith("$H"):
        return "homes the machine ($H)"
    if _STARTUP_STORE.match(line):
        return _acts(line.partition("=")[2], _POWERS)
    if line.startswith("$"):
        return None  # a setting, a query, an unlock: nothing moves
    return _acts(line, _POWERS)


def g2core_powered(text: str) -> str | None:
    """As `grbl_powered`, for g2core: G-code as text or in a JSON `gc` (a homing cycle is
    G28.2 with its axes, which moves); a JSON setting or query, or a `$` text command,
    moves nothing. A line the board would misread is refused anyway (validate_line)."""
    stripped = text.strip()
    if stripped.startswith("{"):
        obj = parse_relaxed(stripped) or {}
        gcode = next((v for k, v in obj.items() if k.lower() == "gc"), None)
        return _acts(normalized(gcode), _POWERS) if isinstance(gcode, str) else None
    if stripped.startswith("$"):
        return None
    return _acts(normalized(stripped), _POWERS)


@dataclass(frozen=True, slots=True)
class StartupBlock:
    n: int
    line: str
    acts: str | None  # what it does that a reset must not do unasked

    def to_json(self) -> dict[str, object]:
        return {"n": self.n, "line": self.line, "acts": self.acts}


def startup_blocks(settings: Mapping[str, str]) -> list[StartupBlock]:
    """The board's stored startup blocks (`$N0`, `$N1`, ... as `$N` lists them), non-empty."""
    blocks = []
    for key, value in settings.items():
        if key.startswith("N") and key[1:].isdigit() and value.strip():
            blocks.append(StartupBlock(int(key[1:]), value, startup_block_acts(value)))
    return sorted(blocks, key=lambda b: b.n)
