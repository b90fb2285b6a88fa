"""Status report keys and g2core's filtered reporting (g2core.md section 4).

The board knows each key's current value (output.py fills a snapshot); this
module decides what a report contains: with `sv` 1 only the values that
changed since they were last reported, except `stat`, which is always
included when it is 3 (stop) or 4 (end); with `sv` 2 everything listed.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

# The board's inputs: digital `in1`..`in8` (0/1) and analogue `ain1`..`ain4`.
DIGITAL_INPUTS = 8
ANALOG_INPUTS = 4
INPUT_KEYS: tuple[str, ...] = tuple(f"in{n}" for n in range(1, DIGITAL_INPUTS + 1)) + tuple(
    f"ain{n}" for n in range(1, ANALOG_INPUTS + 1)
)

# Keys a status report may list (leaf keys only, as on the board).
SR_KEYS: tuple[str, ...] = (
    "line",
    "n",
    "posx",
    "posy",
    "posz",
    "mpox",
    "mpoy",
    "mpoz",
    "ofsx",
    "ofsy",
    "ofsz",
    "feed",
    "vel",
    "unit",
    "stat",
    "macs",
    "cycs",
    "mots",
    "hold",
    "coor",
    "dist",
    "admo",
    "frmo",
    "momo",
    "plan",
    "path",
    "tool",
    "g92e",
    "homx",
    "homy",
    "homz",
    "home",
    "qr",
    *INPUT_KEYS,
)
# The spindle's keys, by the branch the build is of: master's 100.26 `spe` (enable), `spd`
# (direction), `sps` (config_app.cpp:863-865); edge's 101.03 on `spc` (state), `sps`
# (101.03 config_app.cpp:718-719; edge-preview spindle.cpp:487-488).
_SPINDLE_KEYS_MASTER = ("spe", "spd", "sps")
_SPINDLE_KEYS_EDGE = ("spc", "sps")
_EDGE_FROM = 101.0


def spindle_keys(fb: float) -> tuple[str, ...]:
    """The spindle keys of the simulated build: 100.26 is master's, 101 on edge's."""
    return _SPINDLE_KEYS_EDGE if fb >= _EDGE_FROM else _SPINDLE_KEYS_MASTER


DEFAULT_SR: tuple[str, ...] = ("line", "posx", "posy", "posz", "feed", "vel", "unit", "stat")
MAX_SR_KEYS = 39  # NV_MAX_OBJECTS

# Decimal places a value is reported (and compared) with.
_PLACES = {"vel": 2, "feed": 2}
_POSITION_PLACES = 3
_ANALOG_PLACES = 3
_ALWAYS_REPORTED_STATS = (3, 4)


def number(value: float, places: int) -> float | int:
    """A value as g2core prints it: rounded, and without a fraction when it has none."""
    rounded = round(value, places)
    if rounded == int(rounded):
        return int(rounded)
    return rounded


def places(key: str) -> int:
    if key.startswith(("pos", "mpo", "ofs")):
        return _POSITION_PLACES
    if key.startswith("ain"):
        return _ANALOG_PLACES
    return _PLACES.get(key, 0)


def filtered(
    keys: Iterable[str],
    values: Mapping[str, float | int],
    last: dict[str, float | int],
    verbose: bool,
) -> dict[str, float | int]:
    """The report for `keys`; `last` (what was reported before) is updated."""
    out: dict[str, float | int] = {}
    for key in keys:
        value = values[key]
        always = key == "stat" and value in _ALWAYS_REPORTED_STATS
        if verbose or always or last.get(key) != value:
            out[key] = value
            last[key] = value
    return out
