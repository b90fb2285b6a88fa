"""A machine's travel, speeds and accelerations, as read from its board's settings.

Each dialect's session says which settings hold them and reads the answers
(`limit_settings`, `machine_limits`): g2core's `xtn`/`xtm` (travel, machine
coordinates), `xvm` (traverse velocity); grbl's `$130`.. (max travel: machine
coordinates run from -max to 0 with grbl's default build, limits.c), `$110`..
(max rate), `$120`.. (acceleration). What a board does not say is absent.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True, slots=True)
class MachineLimits:
    travel: dict[str, tuple[float, float]] = field(default_factory=dict)  # mm, machine coords
    velocity: dict[str, float] = field(default_factory=dict)  # mm/min, the traverse rate
    acceleration: dict[str, float] = field(default_factory=dict)  # mm/s^2

    def to_json(self) -> dict[str, object]:
        return {
            "travel": {a: list(v) for a, v in self.travel.items()},
            "velocity": dict(self.velocity),
            "acceleration": dict(self.acceleration),
        }
