"""What a simulated board is configured with, and the records it keeps of its traffic."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

AXES: tuple[str, ...] = ("x", "y", "z")
EPS = 1e-6  # mm: positions this close are the same (probe contact, soft limits)


def _default_travel() -> dict[str, float]:
    return {"x": 300.0, "y": 300.0, "z": 100.0}


@dataclass(frozen=True)
class SimConfig:
    """How the simulated g2core behaves; the defaults are a plausible small machine.

    Times are real seconds. `speed_factor` divides every move's duration (a
    factor of 40 runs a one-minute job in 1.5 s); `instant` makes moves finish
    at once, for tests that stream thousands of lines a second.
    """

    planner_depth: int = 16
    speed_factor: float = 1.0
    instant: bool = False
    rapid_rate: float = 6000.0  # mm/min, the speed of G0 and of homing
    feedhold_decel: float = 0.05  # s from `!` to standing still
    status_interval: float = 0.25  # s, the initial `si`
    travel: dict[str, float] = field(default_factory=_default_travel)  # axis -> max mm
    fb: float = 101.06  # firmware build in the banner; 440.xx makes it look like TinyG
    # A board on a UART link (a Due programming port, a USB-serial adapter): SYSTEM
    # READY only when it boots (after 0x18), not when a host opens the port.
    uart: bool = False
    boot_time: float = 0.05  # s the board is gone after a reset (0x18)
    rx_budget: int = 1024  # bytes of unprocessed input per port, like the board's RX ring
    # Entries kept in `received` and `sent` (None: all, for tests). A board that
    # runs for days inside the daemon keeps only the most recent ones.
    history: int | None = None

    def __post_init__(self) -> None:
        if self.planner_depth < 1:
            raise ValueError("planner_depth must be at least 1")
        if self.speed_factor <= 0:
            raise ValueError("speed_factor must be positive")
        if self.history is not None and self.history < 1:
            raise ValueError("history must be at least 1")
        if self.rx_budget < 64:
            raise ValueError("rx_budget must be at least 64 bytes")


Kind = Literal["line", "realtime", "raw"]


@dataclass(frozen=True, slots=True)
class Received:
    """One thing that crossed a port, in arrival order.

    `port` is the configured name of the port ("data" or "control"), not its
    role. `data` is a complete line without its terminator, a single realtime
    byte, or (kind "raw", only in `sent`) bytes injected with `inject_garbage`.
    """

    t: float
    port: str
    data: bytes
    kind: Kind
