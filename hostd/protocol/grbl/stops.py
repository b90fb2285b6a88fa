"""GrblSession's stops, resets and lockout exits: the realtime controls.

A layer of `GrblSession` (session.py). A stop (a cancel, a failed job, a
fault) is a feedhold, then, once a report shows motion at rest, a soft reset
that empties the board (`_begin_stop`, `_stop_reset`, STOP_TIMEOUT); unless a
startup block would act at that reset, when the board is held instead
(`_held`, `_startup_read`). Here too the realtime bytes a client asks for
(`_realtime`, `reset`, `safety_door`), and how a lockout is left (`clear`,
`_lockout_exit`).
"""

from __future__ import annotations

import math
from typing import Any

from hostd.protocol.classes import CommandClass
from hostd.protocol.commands import Realtime
from hostd.protocol.errors import Busy, Rejected
from hostd.protocol.grbl import codec
from hostd.protocol.grbl.books import _REFUSED_BY_SHUTDOWN
from hostd.protocol.grbl.overrides import GrblOverrides
from hostd.protocol.maintenance import startup_blocks
from hostd.protocol.states import MachineState
from hostd.protocol.vocabulary import Context, Excepted, Lane, Phase, Queued, StreamEnd

STOP_TIMEOUT = 2.0  # s for a feedhold to bring motion to rest before the reset goes anyway


class GrblStops(GrblOverrides):
    """Stops, resets, realtime controls and lockout exits (see `GrblSession`)."""

    def _begin_stop(self) -> None:
        """Stop the board and empty it: a jog is cancelled; anything else holds, then resets."""
        if self.model.state is MachineState.JOG:
            self._out.append((Lane.REALTIME, codec.JOG_CANCEL))
            return
        if self._resetting:
            return
        self._out.append((Lane.REALTIME, codec.FEEDHOLD))
        self._start_pending = False  # a stop: no resume of before it may follow
        self._stopping = self.clock() + STOP_TIMEOUT
        # A report printed before the board read the `!` may say Idle while lines it
        # still holds are about to start a move: a reset on its word would stop that move
        # dead (ALARM:3, position lost). Those reports are the answers to `?`s already
        # out, and on grblHAL one nobody asked for (`_unasked_reports`); the one to the `?`
        # written with the `!` comes from the pass that holds, or a later one.
        self._stop_skips = self._asks_open() + self._unasked_reports()
        self._ask_report()

    @staticmethod
    def _at_rest_for_reset(report: codec.StatusReport) -> bool:
        """Motion has stopped: a reset now loses no position (Hold:0 is a finished hold)."""
        return (report.state == "Hold" and report.sub == 0) or report.state in (
            "Idle",
            "Alarm",
            "Check",
            "Door",
            "Sleep",
        )

    def _reset_now(self) -> None:
        self._stopping = None
        self._held = None
        self._forget_holds()
        self._resetting = True
        self._out.append((Lane.REALTIME, codec.RESET))

    def _stop_reset(self, *, timed_out: bool = False) -> None:
        """The reset that ends a stop (a cancel, a failed job, a fault) once motion rests.

        Not while a startup block would move the machine (or start its spindle) at
        the reset, or may (unread, stopped while connecting), unless the config
        allows it: the board stays in its feedhold, nothing more is written
        (`flushing`), and the operator decides, with machine.reset, which runs the
        block.
        """
        moving = [b for b in self.model.startup_blocks or () if b["acts"]]
        # Stopped while connecting (`_connecting_report`): `$N` waits behind the moves.
        unread = self.model.startup_blocks is None and self.phase is Phase.HANDSHAKE
        if (moving or unread) and not self.startup_motion:
            self._stopping = None
            blocks = "; ".join(f"$N{b['n']}={b['line']} {b['acts']}" for b in moving)
            if moving:
                why = f"the startup block {blocks} at every reset; machine.reset runs it"
            else:
                why = (
                    "its startup blocks are not read yet, and may act at a reset; "
                    "machine.reset empties it and runs them"
                )
            self._held = (
                f"{self.id} is held instead of reset: {why}, or allow it with startup_motion = true"
            )
            self._job_log().warning(
                "stop held: a startup block would act" if moving else "stop held: blocks unread",
                blocks=blocks,
            )
            report = {"msg": self._held, "startup_blocks": moving}
            self.model.last_exception = report
            self._events.append(Excepted(report))
            return
        if timed_out:
            self.model.homed = False  # reset in motion, maybe: the position is not to be trusted
        self._reset_now()

    def _startup_read(self) -> None:
        """`$N0=..` read: the snapshot shows the blocks, and a warning says which act."""
        blocks = startup_blocks(self.settings)
        self.model.startup_blocks = [b.to_json() for b in blocks]
        for block in blocks:
            if block.acts:
                self._log.warning(
                    "startup block acts at every reset", n=block.n, line=block.line, acts=block.acts
                )

    def _stop_board(self) -> None:
        self._begin_stop()

    def _realtime(self, command: Realtime) -> None:
        if command is Realtime.FEEDHOLD:
            self._hold_settling = True
            self._start_pending = False  # a newer hold: a resume asked before it is void
            self._resume_asks = 0
            self._out.append((Lane.REALTIME, codec.FEEDHOLD))
            # A `?` read with the `!` would report before the hold (protocol.c): the next
            # poll comes a little later, and soon again until the hold is seen complete.
            self._poll_soon()
        elif command is Realtime.CYCLE_START:
            if self._held is not None:
                # The stopped job's moves are still in the board: `~` would run them.
                raise Busy(self._held)
            if self._hold_settling:
                # grbl takes a cycle start only in Idle or a completed hold, and drops
                # one read with the hold or while it decelerates (gnea/grbl protocol.c:348,
                # protocol_exec_rt_system's EXEC_CYCLE_START): the board would stay
                # held while the host says the job runs. Kept until a report shows
                # the hold complete (`_on_report`), asked for now.
                self._start_pending = True
                self._ask_report()
                return
            self._cycle_start()
        elif command is Realtime.ENQUIRY:
            self._ask_report()
        elif command is Realtime.RESET:
            self.reset()
        else:  # QUEUE_FLUSH, JOB_KILL: grbl has neither; it empties itself by a reset
            if self.stream is not None and not self.stream.done:
                reason = "job killed" if command is Realtime.JOB_KILL else "queue flushed"
                self._end_stream(self.stream, StreamEnd.CANCELLED, None, reason)
            self._begin_stop()

    def reset(self) -> None:
        self._require_open()
        self.halted = False
        self._reset_now()

    def clear(self, token: Any) -> bool:
        """`$X` for an ALARM, once no line of ours is unanswered; an e-stop needs a reset."""
        self._require_ready()
        state = self.model.state
        if state in (MachineState.SHUTDOWN, MachineState.PANIC):
            raise Rejected(
                _REFUSED_BY_SHUTDOWN, f"{self._locked_message()}: only a reset leaves it"
            )
        if state is not MachineState.ALARM:
            return False
        self._refuse_until_reset()
        self._outbox.append(Queued(codec.encode("$X"), CommandClass.CLEAR, token, Context.OWN))
        return True

    def _lockout_exit(self, state: MachineState) -> str:
        """`$X` ends an ALARM, unless it was critical or is an e-stop: then a reset first.

        A homing cycle ends it too where the board homes (`$22` bit 0): gnea/grbl
        system.c:179 takes `$H` in IDLE or ALARM (error:5 with homing off), and a
        cycle that completes leaves ALARM for IDLE. Not an e-stop (SHUTDOWN)."""
        if state is MachineState.INTERLOCK:
            return "close the door, then machine.cycle_start"
        unlock = "machine.clear"
        if state is MachineState.ALARM and self._homes():
            unlock = "machine.clear or machine.home"
        if state is MachineState.ALARM and self._needs_reset is None:
            return unlock
        return f"machine.reset, then {unlock}"

    def _homes(self) -> bool:
        """The board's `$22` (homing cycle enable, bit 0) as its `$$` said; False unread."""
        found = codec.numbers(self.settings.get("22", ""))
        if found is None or len(found) != 1 or not math.isfinite(found[0]):
            return False
        return int(found[0]) & 1 == 1

    def safety_door(self) -> None:
        """0x84 (protocol.c CMD_SAFETY_DOOR): the board enters Door as if its switch opened."""
        self._require_open()
        self._out.append((Lane.REALTIME, codec.SAFETY_DOOR))
