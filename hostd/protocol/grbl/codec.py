"""grbl 1.1 and grblHAL on the wire: what the board prints, and the lines a host may write.

Sources: grblHAL/core report.c (`report_realtime_status`, `report_status_message`,
`report_alarm_message`, the `[...]` feedback), protocol.c
(`protocol_enqueue_realtime_command`: which bytes are picked out of the
stream), grbl.h (the realtime command bytes), stream.h (CRLF line ends); the
grbl wiki's "Interface" page for classic grbl 1.1.

A realtime byte is picked out of the input wherever it appears (protocol.c),
so a `!` inside a comment holds the machine: the host writes no `?`, `!` or
`~` inside a line, and strips comments from a job's lines before it sends
them. Every line the board prints ends in CRLF (`ASCII_EOL`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from enum import Enum

from hostd.protocol.classes import CommandClass
from hostd.protocol.commands import InvalidCommand, Refusal
from hostd.protocol.gcodewords import strip_comments

# Line-mode bytes of grbl.h: `?`, `~`, `!` (legacy, printable) and the 0x8x ones.
STATUS = b"?"
CYCLE_START = b"~"
FEEDHOLD = b"!"
RESET = b"\x18"
SAFETY_DOOR = b"\x84"
JOG_CANCEL = b"\x85"
# The overrides, 0x90-0x9D (grbl.h CMD_OVERRIDE_*), and what each does.
OVERRIDES = {
    "feed_reset": b"\x90",
    "feed_plus_10": b"\x91",
    "feed_minus_10": b"\x92",
    "feed_plus_1": b"\x93",
    "feed_minus_1": b"\x94",
    "rapid_reset": b"\x95",
    "rapid_50": b"\x96",
    "rapid_25": b"\x97",
    "spindle_reset": b"\x99",
    "spindle_plus_10": b"\x9a",
    "spindle_minus_10": b"\x9b",
    "spindle_plus_1": b"\x9c",
    "spindle_minus_1": b"\x9d",
}
OVERRIDE_RANGE = (10, 200)  # percent, feed and spindle (grbl config.h MIN/MAX_*_OVERRIDE)
_RAPIDS = {100: OVERRIDES["rapid_reset"], 50: OVERRIDES["rapid_50"], 25: OVERRIDES["rapid_25"]}
CLASSIC_RX_BUFFER = 128  # grbl 1.1's serial receive buffer (gnea/grbl config.h)
CLASSIC_BLOCKS = 15  # grbl 1.1's planner (BLOCK_BUFFER_SIZE on the 328p)


def check_override(percent: int, what: str) -> None:
    """Refuse a feed or spindle override outside the firmware's own 10..200."""
    low, high = OVERRIDE_RANGE
    if not low <= percent <= high:
        raise InvalidCommand(
            Refusal.BAD_NUMBER, f"a {what} override is {low} to {high} percent, not {percent}"
        )


def override_steps(percent: int, what: str, start: int | None = None) -> list[bytes]:
    """The bytes that take a feed or spindle override to `percent`: from `start`, the
    value the board last reported, or (None) from anywhere, by a reset to 100 first;
    then steps of ten, then of one, all towards `percent`, so that no step leaves
    10..200 (the board would clamp it, protocol.c)."""
    check_override(percent, what)
    origin = 100 if start is None else start
    tens, ones = divmod(abs(percent - origin), 10)
    sign = "plus" if percent >= origin else "minus"
    return [
        *([OVERRIDES[f"{what}_reset"]] if start is None else []),
        *[OVERRIDES[f"{what}_{sign}_10"]] * tens,
        *[OVERRIDES[f"{what}_{sign}_1"]] * ones,
    ]


def override_from_reset(percent: int, what: str, most: int) -> list[bytes]:
    """The bytes that set a feed or spindle override to `percent` whatever it was: a
    reset to 100, then steps of ten and of one, none leaving 10..200. The steps never
    pass `percent` when they and the reset make at most `most` bytes (grblHAL's ring);
    else they are the fewest, a step of ten past it and ones back (100 to 199: ten tens
    and one down, 12 bytes, not nine and nine, 19). At most a reset and 14 steps (100 to
    195: nine tens, five ones), so a ring of 15 always holds them. Written again, they
    set the same value: no report the host reads too early makes them overshoot."""
    check_override(percent, what)
    low, high = OVERRIDE_RANGE
    tens = int((percent - 100) / 10)  # towards 100: never past `percent`
    if 1 + abs(tens) + abs(percent - 100 - 10 * tens) > most:
        tens = min(
            range((low - 100) // 10, (high - 100) // 10 + 1),  # every 100 + 10k in range
            key=lambda k: abs(k) + abs(percent - 100 - 10 * k),
        )
    ones = percent - 100 - 10 * tens
    coarse = "plus" if tens >= 0 else "minus"
    fine = "plus" if ones >= 0 else "minus"
    return [
        OVERRIDES[f"{what}_reset"],
        *[OVERRIDES[f"{what}_{coarse}_10"]] * abs(tens),
        *[OVERRIDES[f"{what}_{fine}_1"]] * abs(ones),
    ]


def rapid_override(percent: int) -> bytes:
    if percent not in _RAPIDS:
        raise InvalidCommand(
            Refusal.BAD_NUMBER, f"a rapid override is 100, 50 or 25 percent, not {percent}"
        )
    return _RAPIDS[percent]


# -- what the board prints -------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Ok:
    """`ok`: the oldest unanswered line was read and executed or planned."""


@dataclass(frozen=True, slots=True)
class Error:
    """`error:N`: the oldest unanswered line was refused."""

    code: int


@dataclass(frozen=True, slots=True)
class Alarm:
    """`ALARM:N`: the board entered its alarm state."""

    code: int


@dataclass(frozen=True, slots=True)
class Welcome:
    """`Grbl 1.1h ['$' for help]` or `GrblHAL 1.1f ['$' or '$HELP' for help]`: after a reset."""

    flavour: str  # "Grbl" or "GrblHAL"
    version: str


@dataclass(frozen=True, slots=True)
class StatusReport:
    """`<Idle|MPos:0.000,0.000,0.000|FS:0,0>`: the state, its substate and the fields."""

    state: str  # Idle, Run, Hold, Jog, Alarm, Door, Check, Home, Sleep, Tool
    sub: int | None  # Hold:0/1, Door:0-4, Alarm:N on grblHAL
    fields: dict[str, str]


@dataclass(frozen=True, slots=True)
class Feedback:
    """`[KIND:text]`: MSG, GC, PRB, VER, OPT, HLP, echo, the `$#` offsets (G54, TLO, ...)."""

    kind: str
    text: str


@dataclass(frozen=True, slots=True)
class Setting:
    """`$N=V`: one line of `$$` (or `$Nn=` startup lines)."""

    key: str
    value: str


@dataclass(frozen=True, slots=True)
class Other:
    """A printable line of no kind above (a startup line's `>G54:ok`, help text)."""

    text: str


@dataclass(frozen=True, slots=True)
class Garbage:
    reason: str
    raw: bytes


Message = Ok | Error | Alarm | Welcome | StatusReport | Feedback | Setting | Other | Garbage

_WELCOME = re.compile(r"(Grbl|GrblHAL) (\S+) \[.*\]")
_FEEDBACK = re.compile(r"\[([A-Za-z0-9.]+):(.*)\]")
_SETTING = re.compile(r"\$(N?\d+)=(.*)")
# Classic grbl keeps these as bits of settings.flags (gnea/grbl settings.c:243-296):
# any value but 0 written sets the flag, and `$$` says 1.
CLASSIC_FLAGS = frozenset({"4", "5", "6", "13", "20", "21", "22", "32"})
_NUMBER = re.compile(r"-?\d+")


def parse(line: bytes) -> Message:
    """One line as the board printed it, without its CRLF."""
    try:
        text = line.decode("ascii")
    except UnicodeDecodeError:
        return Garbage("not valid ASCII", line)
    text = text.strip("\r")
    if text == "ok":
        return Ok()
    if any(c < " " or c == "\x7f" for c in text):
        return Garbage("control characters in a line", line)
    head, _, rest = text.partition(":")
    if head == "error" and _NUMBER.fullmatch(rest):
        return Error(int(rest))
    if head == "ALARM" and _NUMBER.fullmatch(rest):
        return Alarm(int(rest))
    if text.startswith("<") and text.endswith(">"):
        return _status(text[1:-1], line)
    if match := _FEEDBACK.fullmatch(text):
        return Feedback(match[1], match[2])
    if match := _SETTING.fullmatch(text):
        return Setting(match[1], match[2])
    if match := _WELCOME.fullmatch(text):
        return Welcome(match[1], match[2])
    if not text:
        return Other("")
    return Other(text)


def _status(body: str, raw: bytes) -> Message:
    state, *parts = body.split("|")
    name, _, sub = state.partition(":")
    if not name.isalpha() or (sub and not sub.isdigit()):
        return Garbage("a status report with no state", raw)
    fields: dict[str, str] = {}
    for part in parts:
        key, sep, value = part.partition(":")
        if not key:
            return Garbage("a status report field with no name", raw)
        fields[key] = value if sep else ""
    return StatusReport(name, int(sub) if sub else None, fields)


def numbers(text: str) -> list[float] | None:
    """`1.000,-2.500,0` as numbers; None if any is not one."""
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        return None


# -- what the host writes --------------------------------------------------------

_PICKED_OUT = re.compile(r"[?!~]")
# A line with nothing the checks below refuse: printable ASCII, none of grbl's realtime bytes.
# 0x20-0x7E but for 0x21 `!`, 0x3F `?` and 0x7E `~`.
_PRINTABLE_LINE = re.compile(r"[\x20\x22-\x3e\x40-\x7d]*")
_VIEWS = frozenset({"$", "$$", "$#", "$G", "$I", "$N", "$HELP", "$ES", "$ESH", "$EA", "$EAH"})
_CLEARS = frozenset({"$X", "$H"})


_AXIS_LETTERS = frozenset(b"XYZABCUVW")
_WORDS = re.compile(rb"([A-Z])\s*([-+]?[0-9]*\.?[0-9]*)")
MAY_STORE = re.compile(rb"[Gg]\s*0*(?:10|28\.1|30\.1)")  # G10, G28.1, G30.1, maybe
_STORED_KEYS = (b"I", b"RST")  # `$I=` build info, `$RST=` restore (N0/N1 and numbers below)


def homes(line: bytes) -> bool:
    """`$H`, or grblHAL's one-axis `$HX`, `$HYZ`; not `$HELP`."""
    code = line.strip().upper()
    return code.startswith(b"$H") and set(code[2:]) <= _AXIS_LETTERS


def stores(line: bytes) -> bool:
    """The line writes the board's EEPROM or flash (the grbl wiki's "EEPROM Issues").

    `$x=`, `$I=`, `$Nx=`, `$RST=`, `G10 L2`/`L20` (and grblHAL's tool table,
    `G10 L1`/`L10`/`L11`), `G28.1`, `G30.1`. An AVR turns its interrupts off while
    it writes, serial receive included: bytes that arrive meanwhile are lost.
    """
    if line[:1] != b"$" and not MAY_STORE.search(line):
        return False  # most lines: one search, no parse
    code = strip_comments(line.decode("ascii", "replace"), "")[0].strip().upper().encode()
    if code.startswith(b"$"):
        key, eq, _ = code[1:].partition(b"=")
        key = key.strip()
        numbered_line = key.startswith(b"N") and key[1:].isdigit()
        return bool(eq) and (key.isdigit() or key in _STORED_KEYS or numbered_line)
    g: set[float] = set()
    l_words: set[float] = set()
    for letter, value in _WORDS.findall(code):
        try:
            number = float(value)
        except ValueError:
            continue
        if letter == b"G":
            g.add(number)
        elif letter == b"L":
            l_words.add(number)
    return 28.1 in g or 30.1 in g or (10 in g and bool(l_words & {1, 2, 10, 11, 20}))


class GrblLine(Enum):
    """How a client's line is written to a grbl board."""

    REALTIME = "realtime"  # `?`: picked out at once, answered by a status report
    LINE = "line"  # counted against the receive buffer, answered `ok` or `error:N`


def classify(text: str) -> CommandClass:
    """The class of one client line, as grbl reads it (spec: behaviour.md, the class table).

    `?` and the `$` views are queries; `$X` and `$H` are what grbl accepts to
    leave an alarm; everything else (G-code, `$J=`, `$N=V`, `$C`, `$RST`,
    `$SLP`) is an action. M2 and M30 do not clear a grbl alarm.
    """
    upper = text.strip().upper()
    if upper == "?" or upper in _VIEWS:
        return CommandClass.QUERY
    if upper in _CLEARS or (upper.startswith("$H") and upper[2:].isalpha()):
        return CommandClass.CLEAR  # $H, $HX, $HY: homing, one axis or all
    return CommandClass.ACTION


# Printable ASCII without the bytes grbl picks out of a line: `encode`'s one-regex test,
# for the session's per-line path.
printable = _PRINTABLE_LINE.fullmatch
# Job lines as the host numbers them, each ending in LF: `N<number> ` and a text that
# `GrblFlow.encode_job_line` writes as it is (printable, no comment, no blank at its end,
# not a `$`, `{` or `?` line, not an N word of the file's own), all in one match. Atomic
# groups, not `++`, as in gcode.py's: Python 3.11.2 matches those wrongly.
_PLAIN_NUMBERED = re.compile(
    r"(?>(?:N[0-9]++ (?![Nn$?{])[\x20\x22-\x27\x29-\x3a\x3c-\x3e\x40-\x7d]++(?<! )\n)+)"
)
plain_numbered_block = _PLAIN_NUMBERED.fullmatch
# The same lines unnumbered (a board that keeps no N): each is `encode`'s answer as it
# is, with no blank at either end, and neither a `$` line nor a `{` one (whose turn
# `_pump` takes line by line).
_PLAIN_LINES = re.compile(r"(?>(?:(?![ ${])[\x20\x22-\x27\x29-\x3a\x3c-\x3e\x40-\x7d]++(?<! )\n)+)")
plain_block = _PLAIN_LINES.fullmatch


def encode(text: str, *, max_bytes: int = CLASSIC_RX_BUFFER - 1) -> bytes:
    """A line to write: comments removed, no byte the board would pick out, LF-terminated.

    InvalidCommand if it holds a byte grbl does not read as part of a line,
    or would not fit the board's receive buffer with its LF.
    """
    # Flat comments, as protocol.c drops them (an unclosed one to the end of the line),
    # read in linear time: `re.sub(r"\([^)]*\)|;.*")` took quadratic time on "((((".
    code = strip_comments(text, "")[0].strip()
    if _PRINTABLE_LINE.fullmatch(code) is not None and len(code) + 1 <= max_bytes:
        return code.encode() + b"\n"  # every job line: one regex, not a loop over its bytes
    if not code.isascii() or any(c < " " or c == "\x7f" for c in code):
        raise InvalidCommand(Refusal.NOT_TEXT, "only printable ASCII reaches a grbl board")
    if _PICKED_OUT.search(code):
        raise InvalidCommand(
            Refusal.REALTIME,
            "a '?', '!' or '~' inside a line is taken by grbl as a realtime command",
        )
    if len(code) + 1 > max_bytes:
        raise InvalidCommand(
            Refusal.TOO_LONG, f"longer than the board's receive buffer ({max_bytes} bytes)"
        )
    return code.encode() + b"\n"


def setting_write(line: bytes) -> tuple[str, str] | None:
    """`$110=500.000` as written (its LF or not): the setting's number and the value, read
    as the board's own `$110=..` lines are (`_SETTING`); a `$N0=` startup block is none."""
    found = _SETTING.fullmatch(line.decode("ascii", "replace").removesuffix("\n"))
    if found is None or found[1].startswith("N"):
        return None
    return found[1], found[2].strip()
