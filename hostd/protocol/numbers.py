"""Numbers for the board: how far they may go, and the one way the host writes them.

What the board does with a number (g2core source, `g2core/gcode_parser.cpp`,
`json_parser.cpp`, `text_parser.cpp`, `util.h`):

- G-code words are read by `c_atof`, which accumulates the integer part in
  a 32-bit `int`: past 2,147,483,647 it wraps, and `X3000000000` becomes a
  negative move. It knows no exponent: `X1e300` is the word X1 followed by
  the word E300 (an extruder move on builds with Marlin compatibility).
- JSON values are read by `strtod` and `atol`; the integer is compared with
  the float cast to `int32_t` (undefined past 2^31, saturating on ARM) and
  float settings are stored as 32-bit floats (1e300 becomes infinity).
- `$name=value` is read by `strtof` and `atol`, with the same limits.

So every number that reaches the board is finite and below `BOARD_LIMIT`
in magnitude (nine integer digits, well short of 2^31), and the numbers the
host writes itself are rounded to a fixed number of decimals and never use
exponent notation: `F{1e300:g}` would be `F1e+300`.
"""

from __future__ import annotations

import math

from hostd.protocol.refusals import InvalidCommand, Refusal

# |value| < BOARD_LIMIT for every number in a line: nine integer digits at most.
BOARD_LIMIT = 1_000_000_000
# A jog distance (mm, inch or degree), inclusive: 100 m is beyond any machine's
# travel, and the board's 32-bit floats still resolve 0.01 there.
MAX_DISTANCE = 100_000.0
DISTANCE_DECIMALS = 4
# A feed rate (units per minute), inclusive: 1,000,000 mm/min is 16.7 m/s.
MIN_FEED = 0.001
MAX_FEED = 1_000_000.0
FEED_DECIMALS = 3
# A numeric setting value: rounded to six decimals, trailing zeros dropped.
SETTING_DECIMALS = 6


def check_finite(value: int | float, what: str, limit: float = BOARD_LIMIT) -> None:
    """Refuse a value that is not a finite number, or whose magnitude exceeds `limit`.

    `limit` itself is allowed, except for BOARD_LIMIT, which is exclusive.
    """
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise InvalidCommand(Refusal.BAD_NUMBER, f"{what} must be a number, not {value!r}")
    if isinstance(value, float) and not math.isfinite(value):
        raise InvalidCommand(Refusal.BAD_NUMBER, f"{what} must be a finite number, not {value}")
    if abs(value) > limit or (limit == BOARD_LIMIT and abs(value) >= limit):
        bound = f"below {limit:,}" if limit == BOARD_LIMIT else f"at most {limit:,g}"
        raise InvalidCommand(
            Refusal.BAD_NUMBER, f"{what} {_short(value)} is out of range: |value| must be {bound}"
        )


def fixed(value: int | float, decimals: int, what: str, limit: float) -> str:
    """`value` rounded to `decimals` places, as plain digits; never `-0`, never an exponent."""
    check_finite(value, what, limit)
    text = f"{value:.{decimals}f}"
    check_finite(float(text), what, limit)  # rounding can carry past the limit
    if float(text) == 0:
        text = text.lstrip("-")
    return text


def format_distance(value: float, what: str = "distance") -> str:
    """A jog distance: four decimals, |value| <= MAX_DISTANCE."""
    return fixed(value, DISTANCE_DECIMALS, what, MAX_DISTANCE)


def format_feed(value: float) -> str:
    """A feed rate: three decimals, MIN_FEED <= value <= MAX_FEED."""
    text = fixed(value, FEED_DECIMALS, "feed", MAX_FEED)
    if float(text) < MIN_FEED:
        raise InvalidCommand(
            Refusal.BAD_NUMBER, f"feed {_short(value)} is out of range: at least {MIN_FEED}"
        )
    return text


def format_setting(value: int | float, what: str) -> str:
    """A numeric setting value: an integer as is, a float to six decimals, below BOARD_LIMIT."""
    if isinstance(value, int) and not isinstance(value, bool):
        check_finite(value, what)
        return str(value)
    text = fixed(value, SETTING_DECIMALS, what, BOARD_LIMIT)
    whole, _, decimals = text.partition(".")
    return f"{whole}.{decimals.rstrip('0') or '0'}"


def _short(value: int | float) -> str:
    """A value for a message: huge integers are cut, not printed in full."""
    text = repr(value)
    return text if len(text) <= 24 else f"{text[:12]}...({len(text)} digits)"
