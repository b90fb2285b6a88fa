"""The `$n` settings as the firmware defaults have them, and how `$$` prints one.

The board keeps its own copy (`GrblBoard.settings`), made from these at
power-on with the config's values put in; system.py reads and stores them.
"""

from __future__ import annotations

HOMING_PULLOFF = 1.0  # mm, $27; homing toward +: the home position is -pulloff

# $$ as the firmware defaults have it (gnea/grbl defaults.h DEFAULTS_GENERIC; grblHAL
# config.h agrees for these). $10, $20, $21, $22, $32 change behaviour; the rest are kept.
DEFAULTS: dict[int, float] = {
    0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0,
    20: 0, 21: 0, 22: 0, 23: 0, 24: 25.0, 25: 500.0, 26: 250, 27: 1.0, 30: 1000, 31: 0,
    32: 0, 100: 250.0, 101: 250.0, 102: 250.0, 110: 500.0, 111: 500.0, 112: 500.0,
    120: 10.0, 121: 10.0, 122: 10.0, 130: 200.0, 131: 200.0, 132: 200.0,
}  # fmt: skip
FLOAT_SETTINGS = frozenset({11, 12, 24, 25, 27} | set(range(100, 133)))
# Classic grbl keeps these as bits of settings.flags: any non-zero value stores 1.
CLASSIC_FLAGS = frozenset({4, 5, 6, 13, 20, 21, 22, 32})
# HAL $10 (status report options): machine position, buffer state, line numbers,
# feed & speed, pin state, WCO, overrides (config.h DEFAULT_REPORT_*).
HAL_REPORT_MASK = 0b1111111


def setting_text(key: int, value: float) -> str:
    """`$key=` followed by this: three decimals for a float setting, else an integer."""
    return f"{value:.3f}" if key in FLOAT_SETTINGS else str(int(value))
