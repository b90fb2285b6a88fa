"""G2Session's status handling: the board's reports, and what the state they show means.

A layer of `G2Session` (g2core.py). A status report (`{"sr":...}`, or one in
an answer) goes into the model (`_on_status`), but a lockout an exception
report announced stands until a report shows it. A report with a `stat` ends
the wait for a report, may prove a flush, and may complete a job. A change of
state (`_on_state`) asks for `home` when a homing cycle ends, puts the
override factors back at a program end, tells an underflow, drains what a
lockout refuses, and sends again the settings one refused. Here too: which
line the board executes (`_track_executed`), a probe's result, the override
factors (`override`), and which lines are the status poll and its reports
(`status_traffic`). The status codes and the states themselves are in
status.py and states.py.
"""

from __future__ import annotations

import re
from typing import Any

from hostd.protocol.commands import InvalidCommand, Refusal, encode_get, encode_set
from hostd.protocol.g2books import _Own
from hostd.protocol.g2builds import OVERRIDE_RANGES
from hostd.protocol.g2handshake import protocol_settings
from hostd.protocol.g2kills import _FLUSH_CONFIRMED, G2Kills
from hostd.protocol.messages import Response
from hostd.protocol.states import MachineState
from hostd.protocol.status import message
from hostd.protocol.vocabulary import Phase, Probed, Reported

_RESTING_STATES = frozenset({MachineState.READY, *_FLUSH_CONFIRMED})
_TRACKED = ("line", "vel")  # what `_track_executed` reads from the board's automatic reports


class G2Status(G2Kills):
    """The board's status reports and state changes (see `G2Session`)."""

    # -- reports ---------------------------------------------------------------

    def _on_status(self, fields: dict[str, Any], *, requested: bool = False) -> None:
        """A report: automatic (`{"sr":...}`, filtered) or in an answer (`requested`, whole)."""
        if not requested:
            self._auto_sr.update((key, fields[key]) for key in _TRACKED if key in fields)
        before = self.model.state
        changed = self.model.apply_status(fields)
        held = self._held
        if held is not None and "stat" in fields:
            state = self.model.state
            if state is not None and state.is_lockout:
                self._held = None  # the board shows the lockout: its reports rule again
                self._alarm_kill_due = False  # its own kill, if any, came before (:354)
            else:
                # 101.05+ passes through a hold (stat 6/5) before ALARM; 101.02-101.04
                # never enter it: the announced lockout stands until a clear.
                self.model.state = held
                changed = None
        if "stat" in fields:
            self._await_report = False
            self._confirm_flush()
            if self._awaiting_rest:
                self._check_stream_complete(reported=True)
        self._track_motion()
        if changed is not None:
            self._on_state(changed, before)
        if self._moved and self.model.state in _RESTING_STATES:
            here = self.model.machine_position or self.model.position
            self._rest_at, self._moved = dict(here), False  # at rest: moves count from here
        self._track_executed(fields if requested else self._auto_sr)
        self._events.append(Reported(fields, self.model.snapshot()))

    def _track_motion(self) -> None:
        """Whether the board moved since it last rested: a report away from there (its
        machine position, or its work position where it reports no machine position),
        or with a speed. A run with nothing to move starts and ends a cycle where it
        stood: g2core drops a zero-length move and ends the cycle it started for it
        (canonical_machine.cpp:1204-1211, 1360-1367), and a tool change, a dwell or an
        M-code moves no axis."""
        model = self.model
        here = model.machine_position or model.position
        if self._rest_at is None or (model.velocity or 0.0) > 0.0 or here != self._rest_at:
            self._moved = True

    def _track_executed(self, said: dict[str, Any]) -> None:
        """`line` is the runtime's N while the board moves, and only then.

        canonical_machine.cpp (synthetos/g2 1fb5940): `line` reads the ACTIVE_MODEL
        (:2048), which is the parser's model (the last line *read*, possibly far ahead
        in the planner) while the motion state is MOTION_STOP, else the runtime (:354).
        The motion state leaves MOTION_STOP only when a block begins to execute
        (plan_exec.cpp:531-533), but stat says RUN from the moment a move is *parsed*
        (`cm_cycle_start` in `cm_straight_traverse` :1204 and `cm_straight_feed`
        :1360; `cm_get_combined_state` :375). So in the planner's startup, before its
        first block runs, a report says RUN with the line the parser reached, maybe
        the job's last: taken, a job lost then was resumed past lines that never ran.
        `vel` is 0 exactly while the motion state is MOTION_STOP (`cm_get_vel`,
        :2050): only a report of RUN with a speed says which line executes. `said` is
        what the report says of `line` and `vel`: an answer's, whole; for an automatic
        one, the board's own record of its automatic reports (`_auto_sr`), since a
        filtered report leaves out what did not change since the last *automatic*
        one (report.cpp:480; an answer's report, :385, leaves that record alone). The
        merged model would not do: an answer in the planner's startup (`line` 26, the
        parser's) and then a filtered report in motion that leaves out `line` (3, as
        the automatic report before the answer said) merge to line 26 with a speed.
        A moment of motion whose report shows no speed is missed, which keeps
        `line_executed` a lower bound.
        """
        stream = self.stream
        line, speed = _number(said.get("line")), _number(said.get("vel"))
        if (
            stream is not None
            and not stream.done
            and line is not None
            and int(line) > 0
            and speed is not None
            and speed > 0
            and self.model.state is MachineState.RUN
        ):
            stream.executing(int(line))

    def line_running(self) -> int | None:
        """`line` from a report of RUN with a speed (`_track_executed`'s rule: stopped, in
        a hold or before the first block moves, `line` is the last line *read*)."""
        model = self.model
        line, speed = model.line, model.velocity
        if model.state is MachineState.RUN and line and line > 0 and speed and speed > 0:
            return line
        return None

    def _on_probe(self, report: dict[str, Any]) -> None:
        """A probe cycle's result (cycle_probing.cpp `_send_probe_report`): kept and told."""
        probe = self.model.apply_probe(report)
        self._job_log().info("probe", ok=probe["ok"], position=probe["position"])
        self._events.append(Probed(report, probe))

    def _on_state(self, state: MachineState, before: MachineState | None = None) -> None:
        self._job_log().info("controller state", state=state.name)
        if before is MachineState.HOMING:
            self._ask_own(encode_get("home"), _Own.HOMED)  # a homing cycle ended, done or failed
        if state is MachineState.PROGRAM_END and self.model.overrides is not None:
            # A program end puts the feed and traverse factors back to 1.0, the spindle's
            # untouched (_exec_program_finalize calls cm_reset_overrides: edge-preview
            # canonical_machine.cpp:1436-1442, 1632; 100.26 :1617-1624).
            self.model.overrides = {**self.model.overrides, "feed": 100.0, "rapid": 100.0}
        stream = self.stream
        if state is MachineState.RUN and stream is not None:
            stream.at_program_pause = False  # going on from a program pause, if at one
        elif (
            state in _FLUSH_CONFIRMED
            and stream is not None
            and not stream.done
            and self._flush is None
            and not stream.paused  # a pause the board ignored (nothing moving) is no underflow
            and not self._await_report  # the host held the lines back: no starving
            and not self.model.hold  # a hold at rest (101.05+) is no starving either
        ):
            if stream.at_program_pause:
                pass  # still stopped at the program's pause
            elif stream.program_pauses:
                # The stop at an M0 the job wrote. Counted, not flagged until RUN: the board
                # runs the moves before it (RUN reports) after the M0 went out, the first
                # window's with it, and the stop comes only once it reaches the M0.
                stream.program_pauses -= 1
                stream.at_program_pause = True
            elif stream.lines_on_host() and self._moved:
                # The board ran out of moves while the job still had lines on the host
                # (but a `{`-line, which waits on purpose; a run that moved nothing, at
                # rest, M6, G4, starved nothing): reported with the file line it stopped
                # after (behaviour.md, faults).
                line = stream.last_acked_line
                self._detected("underflow", line, f"the controller stopped after file line {line}")
        if state.is_lockout:
            self._drain_for_lockout(state, message)
        elif self._settings_pending and self.phase is Phase.READY:
            self._settings_pending = False
            settings = protocol_settings(self.status_interval, self.signal_keys, self.spindle_keys)
            for setting in settings:
                self._ask_own(encode_set(setting), _Own.REAPPLY)
        self._recheck_waiting()

    def status_traffic(self, line: bytes, written: bool) -> bool:
        """The session's `{"sr":null}` poll, its answer `{"r":{"sr":{...}},...}`, and the
        `{"sr":{...}}` reports the board sends on its own (g2core/report.cpp
        sr_status_report_callback)."""
        if written:
            return _STATUS_POLL(line.strip()) is not None
        return line.startswith((b'{"sr":', b'{"r":{"sr":'))

    # -- overrides -------------------------------------------------------------

    def override(
        self, feed: int | None = None, rapid: int | None = None, spindle: int | None = None
    ) -> None:
        """The override factors as settings (`{"fro":1.2}`), in any state but a lockout.

        A `{`-line of the session's own on the control lane: the board runs it on
        arrival, ahead of queued G-code, so it acts mid-job; the factor applies to the
        blocks planned after it (edge-preview plan_zoid.cpp:145-148). Where the build
        has a writable enable, it is written on with the factor (100.26's are off at
        start). The answer's values become the model's overrides.
        """
        self._require_ready()
        self.admit_action()  # a board in a lockout refuses every SET: 204/205/206 here
        asked = {"feed": feed, "rapid": rapid, "spindle": spindle}
        keys, enables = self.build.override_keys, self.build.override_enables
        values: dict[str, Any] = {}
        for what, percent in asked.items():
            if percent is None:
                continue
            low, high = OVERRIDE_RANGES[what]
            if not low <= percent <= high:
                raise InvalidCommand(
                    Refusal.BAD_NUMBER,
                    f"a g2core {what} override is {low} to {high} percent, not {percent}",
                )
            if what in enables:
                values[enables[what]] = 1
            values[keys[what]] = round(percent / 100.0, 3)
        self._ask_own(encode_set(values), _Own.OVERRIDES)

    def _read_overrides(self) -> None:
        self._ask_own(encode_get(*self.build.override_keys.values()), _Own.OVERRIDES)

    def _overrides_answered(self, response: Response) -> None:
        """The factors the board answered with (what it stored), as percentages."""
        if not response.ok:
            self._log.warning("override settings refused", status=response.status)
        now = dict(self.model.overrides or {})
        for what, key in self.build.override_keys.items():
            value = response.body.get(key)
            if isinstance(value, int | float) and not isinstance(value, bool):
                now[what] = round(float(value) * 100.0, 1)
        if now:
            self.model.overrides = now
        self.model.override_reports += 1
        self.override_answers += 1  # the answer is what the board stored: no asking again


# `{"sr":null}` as the session writes it, or as an operator may (`{sr:n}`, `{"sr":""}`).
_STATUS_POLL = re.compile(rb'\{\s*"?sr"?\s*:\s*(?:n|null|"")\s*\}', re.IGNORECASE).fullmatch


def _number(value: Any) -> float | None:
    """A report's number, or None for anything else (a bool is no number here)."""
    if isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    return None
