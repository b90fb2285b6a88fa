"""What g2core does differently from one firmware build to the next, as its source shows.

hostd accepts g2core builds from 100 (`fb`, checked in g2handshake.py). Within
that range the board's answers to a kill, a flush, an alarm and a feedhold at
rest changed twice, and the session (g2core.py) and the simulator (hostd/sim)
both read the rules of the board they talk to, or are, from here. Each rule
cites the source it rests on (synthetos/g2 at the tag or commit that set the
build; docs/protocol.md has the table with lines):

- before 101.02 (tags 100.26 and 101.01): ^D is `cm_alarm(STAT_KILL_JOB, ...)`
  (controller.cpp), an ALARM with no flush of the serial input: every line
  still queued is read and answered 204. `cm_alarm` sets MACHINE_ALARM at once
  (canonical_machine.cpp). There is no `gc2` (config_app.cpp has only `gc`).
  `!` is honoured only while something moves.
- 101.02 to 101.04 (tag 101.03): ^D is a job kill that flushes the input of the
  port the ^D came in on (`xio_flush_to_command`); `cm_alarm` and `cm_shutdown`
  only request a feedhold whose exit action `_run_alarm` does nothing
  (cycle_feedhold.cpp): the board never enters ALARM or SHUTDOWN.
- from 101.05 (edge-preview, 101.06): `cm_alarm` requests a feedhold, honoured
  at rest too; once it holds, `_run_alarm` kills the job (its own `er` 207) and
  only then sets ALARM. `!` at rest is a hold with no change of `stat`.
  A `%` flushes every data port once held (`xio_flush_device`).

The changes between 101.03 and 101.06 landed in commits of 2019-10/11 ("Tidy
up alarm and shutdown recovery", 101.05 set on 2019-11-14); no 101.04 was
tagged. A board reporting 101.04 is given 101.03's rules.
"""

from __future__ import annotations

from dataclasses import dataclass

KILL_IS_JOB_KILL = 101.02  # from here ^D kills the job instead of raising ALARM
# From 101.02 the override settings are `fro`/`tro`/`spo` (before: `mfo`/`mto`/`sso`).
OVERRIDES_RENAMED = 101.02
ALARM_THROUGH_HOLD = 101.05  # from here an alarm holds first, then kills, then is ALARM


@dataclass(frozen=True, slots=True)
class Build:
    """The rules of one g2core build that a host can see on the wire."""

    fb: float

    @property
    def kill_alarms(self) -> bool:
        """^D raises ALARM (`er` 207 "EOT Received") and flushes nothing: each queued line
        is answered 204 (100.26 controller.cpp:259, canonical_machine.cpp:963)."""
        return self.fb < KILL_IS_JOB_KILL

    @property
    def alarm_is_state(self) -> bool:
        """An alarm-class exception ends in ALARM (SHUTDOWN): not on 101.02-101.04, whose
        `_run_alarm` does nothing (101.03 cycle_feedhold.cpp:324)."""
        return self.fb < KILL_IS_JOB_KILL or self.fb >= ALARM_THROUGH_HOLD

    @property
    def alarm_holds_first(self) -> bool:
        """The alarm's own feedhold runs first, and ALARM follows it after the board's own
        job kill and `er` 207 (edge-preview alarm.cpp:172, cycle_feedhold.cpp:354)."""
        return self.fb >= ALARM_THROUGH_HOLD

    @property
    def hold_at_rest(self) -> bool:
        """`!` at rest is a hold: `hold` 10, `stat` unchanged, no data line read until
        `~`, `%` or ^D (edge-preview controller.cpp:279, cycle_feedhold.cpp:597, :827)."""
        return self.fb >= ALARM_THROUGH_HOLD

    @property
    def flush_reads_every_data_port(self) -> bool:
        """A `%` flushes the input of every data port once held (edge-preview
        cycle_feedhold.cpp:473); before, only the port the `%` came in on."""
        return self.fb >= ALARM_THROUGH_HOLD

    @property
    def in_hold_gcode(self) -> bool:
        """`{gc2:...}` runs G-code inside a hold: from 101.02 (absent in 100.26
        config_app.cpp, present in 101.03)."""
        return self.fb >= KILL_IS_JOB_KILL

    @property
    def override_keys(self) -> dict[str, str]:
        """The settings that hold the feed, rapid (traverse) and spindle override factors.

        100.26 `config_app.cpp:847,849,862` (`mfo`, `mto`, `sso`); 101.02
        `config_app.cpp:703,723,725` and edge-preview `config_app.cpp:993,995`,
        `spindle.cpp:486` (`fro`, `tro`, `spo`).
        """
        if self.fb < OVERRIDES_RENAMED:
            return {"feed": "mfo", "rapid": "mto", "spindle": "sso"}
        return {"feed": "fro", "rapid": "tro", "spindle": "spo"}

    @property
    def override_enables(self) -> dict[str, str]:
        """The enables a host can write, by override. 100.26's are off at start
        (`cm_reset_overrides`, canonical_machine.cpp:1620,1622; spindle.h:61) and
        written with `set_01` (config_app.cpp:846,848,861). From 101.02 `froe` and
        `troe` are read-only (their table entry's setter is `cm_get_froe`/`cm_get_troe`,
        101.02 config_app.cpp:722,724) and on (`cm_reset_overrides`, edge-preview
        canonical_machine.cpp:1438,1440); `spoe` is written by `sp_set_spoe`
        (edge-preview spindle.cpp:248)."""
        if self.fb < OVERRIDES_RENAMED:
            return {"feed": "mfoe", "rapid": "mtoe", "spindle": "ssoe"}
        return {"spindle": "spoe"}


# The override factors' bounds, in percent: planner.h FEED_OVERRIDE_MIN/MAX (0.05-2.00),
# TRAVERSE_OVERRIDE_MIN/MAX (0.05-1.00); spindle.h (100.26, 101.03) and
# settings_default.h:117-122 (edge-preview) SPINDLE_OVERRIDE_MIN/MAX (0.05-2.00).
OVERRIDE_RANGES = {"feed": (5, 200), "rapid": (5, 100), "spindle": (5, 200)}

NEWEST = Build(101.06)
