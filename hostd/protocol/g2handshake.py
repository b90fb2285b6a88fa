"""g2core's handshake: what a board must be, what it is told, and how long it is given.

G2Session (g2connection.py) runs the steps (g2core.md section 10) on every open
and after every reset: the SYSTEM READY banner, or after `BANNER_WAIT` on a
link that prints none a version request; the firmware build checked
(`check_firmware`); which spindle keys it has (`SPINDLE_KEYS`); the protocol
settings (`protocol_settings`), one at a time; `{home:n}`; a full status
report. Only then is the board ready.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from hostd.protocol.errors import NotConnected

# The status report list the handshake sets: the board reports these on change.
STATUS_KEYS = (
    *("stat", "line", "posx", "posy", "posz", "mpox", "mpoy", "mpoz", "vel", "feed", "unit"),
    *("coor", "dist", "frmo", "momo", "hold", "tool", "home"),
)
# The spindle's keys differ by branch, not by build number (so `fb` cannot pick them):
# master's 100.26 has `spe` (enable: 0 off, 1 on, 2 paused), `spd` (direction: 0 CW,
# 1 CCW) and `sps` (config_app.cpp:863-865; spindle.h:37-46); edge from 101.03 has `spc`
# (0 off, 1 CW, 2 CCW, 3 paused) and `sps` (101.03 config_app.cpp:718-719, spindle.h:49-53;
# edge-preview spindle.cpp:487-488). A key a board lacks is refused whole, the status report
# list with it (json_parser.cpp:167-169), so the handshake asks for each set's first key
# until one is answered, and lists that set; a board with neither reports no spindle.
SPINDLE_KEYS: tuple[tuple[str, ...], ...] = (("spc", "sps"), ("spe", "spd", "sps"))
BANNER_WAIT = 1.0  # s for a banner before asking the version (a UART link prints none)
OLDEST_BUILD = 100.0  # g2core builds before 100 had other status codes
TINYG_BUILDS = 400.0  # TinyG's builds are 400 and up


def protocol_settings(
    status_interval: float, signal_keys: Iterable[str], spindle_keys: Iterable[str] = ()
) -> list[dict[str, Any]]:
    """The settings the handshake sends, one at a time, and sends again once a lockout that
    refused them ends: `status_interval` in seconds; `signal_keys` and the board's
    `spindle_keys` (one of SPINDLE_KEYS, or none) added to the report list."""
    return [
        {"ej": 1},
        {"jv": 4},
        {"sv": 1},
        {"qv": 0},
        {"si": round(status_interval * 1000)},
        {"sr": dict.fromkeys((*STATUS_KEYS, *spindle_keys, *signal_keys), True)},
    ]


def check_firmware(fb: float | None) -> None:
    """g2core from build 100 only: TinyG's codes differ, and before 100 so did g2core's."""
    if fb is None:
        raise NotConnected("the controller did not say its firmware build (fb)")
    if fb >= TINYG_BUILDS:
        raise NotConnected(
            f"TinyG firmware (build {fb:g}) is not supported: its status codes differ from g2core's"
        )
    if fb < OLDEST_BUILD:
        raise NotConnected(
            f"g2core build {fb:g} is older than {OLDEST_BUILD:.2f}, whose status codes hostd "
            "relies on (204 meant something else before): update the firmware"
        )
