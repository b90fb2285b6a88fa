"""G-code words the board would misread, and the host's own G-code (the jog line).

How the board reads a G-code line (g2core `gcode_parser.cpp`, `util.h`):
`(...)` comments are dropped, and `;` or `%` end the line; a checksum
starts at `*`; every space and every character but letters, digits, `.`
and `-` is dropped; each word is a letter and a number read by `c_atof`,
whose integer part is a 32-bit `int` and which has no exponent. Hence the
rules, each a refusal of the whole line (BAD_NUMBER unless said otherwise):

- A number's integer part has at most nine digits, leading zeros not
  counted (below 1,000,000,000; the board wraps past 2,147,483,647, so
  `X3000000000` would move the other way). That holds for N words too (the
  board's own limit for N is 2,000,000,000).
- No exponent: a digit or `.` directly followed by `e`/`E` and a digit, sign
  or `.` (`X1e3`, `X2.5E-1`) is refused. The board reads `X1e300` as X1
  and a word E300, an extruder move on Marlin-compatible builds. An E word
  is written with a space before it: `G1 X1 E5`.
- No numbers run together: digits, a space, then more digits (`X1 000`) are
  refused; the board drops the space and reads X1000.
- No active comments (ACTIVE_COMMENT): a comment that starts `({` or
  `(msg` (any case) is JSON the board runs as a command of its own, outside
  every rule the host applies to JSON lines, and a line holding only one
  gets two answers.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping

from hostd.protocol.gcodewords import strip_comments
from hostd.protocol.numbers import format_distance, format_feed
from hostd.protocol.refusals import InvalidCommand, Refusal

JOG_AXES = ("x", "y", "z", "a", "b", "c")
INTEGER_DIGITS = 9

# The common case, checked in one match: words of a letter other than E and a
# number of at most nine integer digits, no comments. Anything else is read in full.
# Possessive (`*+`, `?+`): no part of a word can be given back to the next one, so
# backtracking finds nothing more, and the match takes half the time.
_PLAIN_WORDS = r"(?:[A-DF-Za-df-z][ \t]*+[-+]?+[0-9]{0,9}+(?:\.[0-9]*+)?+[ \t]*+)++"
_PLAIN = re.compile(_PLAIN_WORDS)
# Job lines as the host numbers them, each ending in LF: `N<number> ` and plain words,
# the first not an N word of the file's own (it would be renumbered). `_PLAIN` of each
# line, all in one match (`plain_numbered_block`). The lines' repeat is atomic, not `++`:
# a line can fail part of the way in, which Python 3.11.2 matches wrongly (test_patterns.py).
_NUMBERED = r"(?>(?:N[0-9]++ (?![Nn]){words}\n)+)"
_PLAIN_NUMBERED = re.compile(_NUMBERED.format(words=_PLAIN_WORDS))
# The same for a block with no tab, almost every file's: a blank is then a space, and `re`
# counts a run of one character in a tighter loop than a run of a set (a fifth of the
# match's time, at every job line; docs/performance.md).
_PLAIN_NUMBERED_SPACED = re.compile(_NUMBERED.format(words=_PLAIN_WORDS.replace("[ \\t]", " ")))
_ACTIVE_COMMENT = re.compile(r"\((?:\{|msg)", re.IGNORECASE)
# The board: `(` to `)` is a comment (gcodewords.strip_comments); `;` or `%` ends the
# line; `*` starts a checksum. Every pattern here is linear: no two ways to match a text.
_LINE_END = re.compile(r"[;%*]")
_EXPONENT = re.compile(r"[0-9.][eE][-+.0-9]")
_RUN_TOGETHER = re.compile(r"[0-9.][ \t]+[0-9.]")
_DROPPED = re.compile(r"[^A-Za-z0-9.\-]")
# An integer part: digits not preceded by a digit or a point (those are decimals).
_INTEGER_PART = re.compile(r"(?<![0-9.])[0-9]+")


# `is_plain` as a bound method, for the per-line paths that would otherwise pay a call more.
plain_match = _PLAIN.fullmatch


def plain_numbered_block(block: str) -> re.Match[str] | None:
    """Numbered job lines, each ending in LF, whose words are all plain (`is_plain`)."""
    return (_PLAIN_NUMBERED if "\t" in block else _PLAIN_NUMBERED_SPACED).fullmatch(block)


def is_plain(text: str) -> bool:
    """Plain words only (the common case above): nothing in it the board could misread."""
    return _PLAIN.fullmatch(text) is not None


def check_gcode(text: str) -> None:
    """Refuse a G-code line the board would misread (the rules above)."""
    if _PLAIN.fullmatch(text):
        return  # every job line takes this path: it must stay cheap
    _check_words(text)


def _check_words(text: str) -> None:
    """The full reading: every rule, whatever the line looks like."""
    active = _ACTIVE_COMMENT.search(text)
    if active is not None:
        raise InvalidCommand(
            Refusal.ACTIVE_COMMENT,
            f"an active comment {text[active.start() : active.start() + 12]!r}...: the board runs "
            "its JSON as a command of its own; send JSON as its own line",
        )
    words = _code_part(text)
    exponent = _EXPONENT.search(words)
    if exponent is not None:
        raise InvalidCommand(
            Refusal.BAD_NUMBER,
            f"{_around(words, exponent.start())!r} looks like exponent notation: the board has "
            "none, and reads X1e3 as X1 and a word E3; write the number in full, "
            "or a space before an E word",
        )
    together = _RUN_TOGETHER.search(words)
    if together is not None:
        raise InvalidCommand(
            Refusal.BAD_NUMBER,
            f"{_around(words, together.start())!r}: numbers separated only by spaces, "
            "which the board drops and reads as one number",
        )
    for m in _INTEGER_PART.finditer(_DROPPED.sub("", words)):
        digits = m.group().lstrip("0")
        if len(digits) > INTEGER_DIGITS:
            raise InvalidCommand(
                Refusal.BAD_NUMBER,
                f"a number with {len(digits)} integer digits ({digits[:12]}...): the board "
                f"reads at most {INTEGER_DIGITS} safely (it wraps past 2,147,483,647)",
            )


def jog_line(axes: Mapping[str, float], feed: float) -> str:
    """`G91 G1 X1.5000 F600.000`: a relative move, in the board's fixed-decimal words."""
    return f"G91 G1 {jog_words(axes, feed)}"


def jog_words(axes: Mapping[str, float], feed: float) -> str:
    """`X1.5000 F600.000`: a jog's distances and feed, checked, in fixed decimals."""
    if not axes:
        raise InvalidCommand(Refusal.EMPTY, "a jog needs at least one axis")
    words = []
    for axis, distance in axes.items():
        if axis not in JOG_AXES:
            raise InvalidCommand(Refusal.UNREADABLE, f"unknown axis {axis!r}")
        words.append(f"{axis.upper()}{format_distance(distance, f'{axis} distance')}")
    return f"{' '.join(words)} F{format_feed(feed)}"


def _code_part(text: str) -> str:
    """The line without its comments, up to where the board stops reading words."""
    code, _ = strip_comments(text)
    end = _LINE_END.search(code)
    return code if end is None else code[: end.start()]


def _around(text: str, at: int) -> str:
    start = max(0, at - 6)
    return text[start : at + 6].strip()


HOME_AXES = ("x", "y", "z")  # what "all axes" homes: the axes both sims and boards have
WCS_P = {"G54": 1, "G55": 2, "G56": 3, "G57": 4, "G58": 5, "G59": 6}


def axes_words(axes: Iterable[str]) -> str:
    """`X0 Y0`: each axis named, at zero."""
    return " ".join(f"{a.upper()}0" for a in axes)


def short_number(value: float) -> str:
    """A value in at most four decimals, without trailing zeros (`1.5`, `0`, `-2.25`)."""
    text = f"{value:.4f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text


def work_zero_line(p: int, axes: Mapping[str, float]) -> str:
    """`G10 L20 P<p>`: the current position reads as given, in coordinate system `p`."""
    words = " ".join(f"{a.upper()}{short_number(v)}" for a, v in axes.items())
    return f"G10 L20 P{p} {words}"
