"""G2Session's lockouts: ALARM, SHUTDOWN and PANIC, announced, shown and cleared.

A layer of `G2Session` (g2core.py). A lockout announced by an exception report
(`_announced`) stands until a report shows it or a clear succeeds
(`_cleared`): a board passes through a hold first (101.05+), or on
101.02-101.04 never gets there, and then the session stops it itself (^D).
A 204/205/206 answer says the board is locked out even before a report does
(`_refused_in_lockout`). A clear (`clear`) goes on the data port once no data
line of ours is unanswered (g2flow.py `_pump`). An `er` 207 is read here
(`_on_kill_report`): the alarm's own job kill (101.05+), the ALARM a ^D
makes before 101.02, or a kill of ours.
"""

from __future__ import annotations

from typing import Any

from hostd.protocol.classes import CommandClass, classify
from hostd.protocol.commands import Realtime, encode_clear
from hostd.protocol.errors import Rejected
from hostd.protocol.g2books import _Own
from hostd.protocol.g2status import G2Status
from hostd.protocol.messages import ExceptionReport
from hostd.protocol.states import MachineState
from hostd.protocol.status import Status
from hostd.protocol.vocabulary import Context, Excepted, Queued

_LOCKOUT_REJECTIONS = frozenset(
    {
        Status.COMMAND_REJECTED_BY_ALARM,
        Status.COMMAND_REJECTED_BY_SHUTDOWN,
        Status.COMMAND_REJECTED_BY_PANIC,
    }
)


class G2Lockouts(G2Status):
    """The board's lockouts and the `er` 207 of a kill (see `G2Session`)."""

    def _announced(self, lockout: MachineState) -> None:
        """An exception report of the alarm, shutdown or panic class: locked out from now.

        How the board gets there depends on its build (g2builds.py): at once
        before 101.02; through a hold, its own job kill and `er` 207 from 101.05;
        never on 101.02-101.04, whose board would run the next line it reads, so
        hostd stops it itself (^D) and keeps its own lockout until a clear.
        """
        build = self.build
        stop = False
        if lockout is not MachineState.PANIC and self.model.state is not lockout:
            if build.alarm_holds_first and not self.model.hold and not self._kills_unseen:
                # Its hold ends in a job kill of its own; none when a hold (ours, or a
                # kill's) is already under way: cm_request_feedhold ignores it then.
                self._alarm_kill_due = True
            stop = not build.alarm_is_state
        self._held = lockout
        self.model.state = lockout
        self._on_state(lockout)  # the job ends failed with the lockout's code first
        if stop:
            self._write_realtime(Realtime.JOB_KILL)

    def _on_kill_report(self, report: ExceptionReport) -> bool:
        """An `er` 207; True when it is accounted here and is no new exception.

        - From 101.05 an alarm's hold ends in a job kill of the board's own: its
          207 follows the alarm's report and is a consequence of it (it must not
          replace the alarm's reason, nor stand for a kill of ours).
        - In a lockout a 207 tells nothing new either: the reason stays.
        - Before 101.02 our ^D is an ALARM ("EOT Received"): a lockout of ours,
          which we clear once its lines are answered.
        - Otherwise it may be one of our ^D's (or several that merged: one
          `_run_job_kill` clears every request made before it, cycle_feedhold.cpp
          :523,553). It is told as an exception; the fence behind the ^D, not
          this report, shows what the kill discarded.
        """
        if self._alarm_kill_due:
            self._alarm_kill_due = False
            self._job_log().info("the alarm's own job kill", msg=report.message)
            return True
        locked = self._held is not None or (self.model.state and self.model.state.is_lockout)
        if self.build.kill_alarms and not locked:
            # Whoever wrote the ^D, the board is in ALARM now (cm_alarm, 100.26).
            self.model.apply_exception(report)
            self._events.append(Excepted(report.fields))
            self._held = MachineState.ALARM
            self.model.state = MachineState.ALARM
            self._on_state(MachineState.ALARM)
            if self._kill_alarm:  # ours: cleared once the lines it caught are answered
                clear = Queued(encode_clear(), CommandClass.CLEAR, _Own.CLEAR, Context.OWN)
                self._outbox.append(clear)
            self._await_report = True
            self._query_status()
            return True
        if self._kills_unseen > 0:
            self._kills_unseen -= 1
            if self._held is None and not (self.model.state and self.model.state.is_lockout):
                self.model.apply_exception(report)
                self._events.append(Excepted(report.fields))
            return True
        if locked:
            self._job_log().info("a job kill in a lockout", msg=report.message)
            return True
        return False

    def _cleared(self) -> None:
        """A clear was answered OK: a lockout of ours ends; a report says where the board is.

        Not while a 101.05+ alarm's hold still runs: `cm_clear` finds no ALARM yet
        and does nothing, and the board enters ALARM once held.
        """
        if not self._alarm_kill_due:
            self._held = None
        self._kill_alarm = False
        self._await_report = True
        self._query_status()

    def _refused_in_lockout(self, status: Status) -> None:
        """A 204/205/206 answer says the board is locked out, even before any report does."""
        state = self.model.state
        lockout = _LOCKOUT_OF[status]
        if state is lockout or self._held is not None:
            return
        if state is not None and state.is_lockout and lockout is not MachineState.PANIC:
            return
        self.model.state = lockout
        self._on_state(lockout, state)

    def clear(self, token: Any) -> bool:
        """`{clear:n}` for ALARM or SHUTDOWN, once no data line of ours is unanswered.

        False if there is nothing to clear; PANIC is refused (only a reset leaves it).
        """
        self._require_ready()
        state = self.model.state
        if state is MachineState.PANIC:
            raise Rejected(Status.COMMAND_REJECTED_BY_PANIC, "PANIC is left only by a reset")
        if state not in (MachineState.ALARM, MachineState.SHUTDOWN):
            return False
        self._outbox.append(Queued(encode_clear(), CommandClass.CLEAR, token, Context.OWN))
        return True


_CLEAR = encode_clear()


_LOCKOUT_OF = {
    Status.COMMAND_REJECTED_BY_ALARM: MachineState.ALARM,
    Status.COMMAND_REJECTED_BY_SHUTDOWN: MachineState.SHUTDOWN,
    Status.COMMAND_REJECTED_BY_PANIC: MachineState.PANIC,
}


def _clears(encoded: bytes) -> bool:
    """A clear in another form (`$clear`, `M30`...): on 101.02-101.04 the board, never in
    ALARM, runs it as a plain line, and its OK ends the lockout hostd kept."""
    cls = classify(encoded.decode("latin-1").strip())
    return cls is CommandClass.CLEAR or cls is CommandClass.PROGRAM_END
