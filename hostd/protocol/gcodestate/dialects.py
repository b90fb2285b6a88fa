"""Where the controllers read the same G-code differently: one table, written once.

Each row is checked against the controller's source (g2core `canonical_machine.cpp`,
`plan_arc.h`; grbl 1.1 `gcode.c`) or, for LinuxCNC, against its interpreter `rs274`
(tests/protocol/test_gcodestate_rs274.py). docs/gcode.md explains each one.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Dialect:
    name: str
    # M2/M30: what program end resets (RS274/NGC 3.6.1 lists G54, G92, G17, G90, G94, M5,
    # M9 and G1; every controller keeps some of it).
    end_clears_g92: bool  # g2core suspends G92 (like G92.2); LinuxCNC and grbl keep it
    end_motion: str  # the motion mode after program end: G1 (NIST), G80 (g2core)
    end_zeroes_feed: bool  # LinuxCNC sets F0 at program end
    end_resets_arc_distance: bool  # g2core: back to G91.1
    # F: LinuxCNC keeps the number, which then reads in the current units (F100 in G21,
    # then G20, is 100 in/min); g2core and grbl convert F to mm/min when they read it.
    feed_follows_units: bool
    # g2core reads F before the G20/G21 of the same block: `G20 F10` from G21 is 10 mm/min.
    feed_before_units: bool
    # G28/G30 with axis words: LinuxCNC sends only those axes home, g2core and grbl all.
    home_only_named_axes: bool
    # G10 L20: LinuxCNC and grbl take G92 into account (work = the value afterwards);
    # g2core does not (offset = machine - value).
    l20_uses_g92: bool
    # An arc whose end is not on its circle (I/J/K form): refused when the two radii differ
    # by more than `arc_abs_max` mm, or by more than `arc_abs_min` mm and `arc_rel` of the
    # radius. LinuxCNC's limits were measured with rs274 (2.9.0~pre1), its defaults.
    arc_abs_max: float
    arc_abs_min: float
    arc_rel: float
    # Codes this controller refuses (a warning, and the model does nothing for them).
    unsupported: frozenset[str]


LINUXCNC = Dialect(
    name="linuxcnc",
    end_clears_g92=False,
    end_motion="G1",
    end_zeroes_feed=True,
    end_resets_arc_distance=False,
    feed_follows_units=True,
    feed_before_units=False,
    home_only_named_axes=True,
    l20_uses_g92=True,
    arc_abs_max=2.84,
    arc_abs_min=0.0284,
    arc_rel=0.001,
    unsupported=frozenset({"G28.2", "G28.3"}),
)

G2CORE = Dialect(
    name="g2core",
    end_clears_g92=True,
    end_motion="G80",
    end_zeroes_feed=False,
    end_resets_arc_distance=True,
    feed_follows_units=False,
    feed_before_units=True,
    home_only_named_axes=False,
    l20_uses_g92=False,
    arc_abs_max=1.0,
    arc_abs_min=0.005,
    arc_rel=0.001,
    unsupported=frozenset(
        {"G33", "G41", "G42", "G43.1", "G76", "G95", "G96", "G97", "M61"}
        | {f"G{n}" for n in range(81, 90)}
    ),
)

GRBL = Dialect(
    name="grbl",
    end_clears_g92=False,
    end_motion="G1",
    end_zeroes_feed=False,
    end_resets_arc_distance=False,
    feed_follows_units=False,
    feed_before_units=False,
    home_only_named_axes=False,
    l20_uses_g92=True,
    arc_abs_max=0.5,
    arc_abs_min=0.005,
    arc_rel=0.001,
    unsupported=frozenset(
        {"G28.2", "G28.3", "G33", "G41", "G42", "G43", "G59.1", "G59.2", "G59.3"}
        | {"G61.1", "G64", "G76", "G90.1", "G92.2", "G92.3", "G95", "G96", "G97", "M6", "M61"}
        | {f"G{n}" for n in range(81, 90)}
    ),
)

DIALECTS = {d.name: d for d in (LINUXCNC, G2CORE, GRBL)}
