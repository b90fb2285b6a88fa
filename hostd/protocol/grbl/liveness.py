"""GrblSession's clock: the status polls, the heartbeat and the link's liveness.

A layer of `GrblSession` (session.py). grbl pushes no status: `tick` asks `?`
every `status_interval` (and while a board found busy holds the handshake
back), asks again a `?` unanswered within `heartbeat`, ends a handshake that
took too long, and gives the link up only after
`link_silence` seconds without a byte and SILENT_QUERIES unanswered `?`s
(`_lost_at`); more while a line writes EEPROM or flash (STORAGE_QUIET) or the
board homes (`_silence_allowed`). `next_deadline` says when `tick` is next
due. Which lines are the poll and its reports: `status_traffic`.
"""

from __future__ import annotations

from hostd.protocol.grbl import codec
from hostd.protocol.grbl.books import SILENT_QUERIES, _Own
from hostd.protocol.grbl.connection import GrblConnection
from hostd.protocol.grbl.words import homing_time_bound
from hostd.protocol.states import MachineState
from hostd.protocol.vocabulary import Phase

# s of silence allowed on top of `link_silence` while a line writes EEPROM or flash: an
# AVR writes a byte in 3.4 ms with its interrupts off (`$RST=*` rewrites ~1 KB); an STM32
# erases a flash sector in 1-2 s.
STORAGE_QUIET = 2.5

_MODES_POLL = codec.encode("$G")


class GrblLiveness(GrblConnection):
    """Polls, heartbeat and silence (see `GrblSession`)."""

    def status_traffic(self, line: bytes, written: bool) -> bool:
        """`?` (grbl.h CMD_STATUS_REPORT) and the `<...>` report that answers it
        (report.c report_realtime_status); and the session's own `$G` after a client's
        line or a job (`_modes_changed`), its `[GC:...]` and its `ok`: a poll of the
        modes the status topic shows, not a line anyone sent. A client's own `$G` is
        not: the written line must be the one booked for the session, and a line read
        is asked about before it is taken, while that `$G` is the oldest unanswered.
        """
        if written:
            if line == _MODES_POLL:  # one comparison first: a client's lines are not
                return any(e.line is line and e.source is _Own.MODES for e in self._inflight)
            return line.strip() == codec.STATUS
        if line[:1] == b"<":
            return line.rstrip()[-1:] == b">"
        inflight = self._inflight
        return (
            bool(inflight)
            and inflight[0].source is _Own.MODES
            and (line == b"ok" or line.startswith(b"[GC:"))
        )

    def modes_pending(self) -> bool:
        """The session's own `$G` (`_modes_changed`) is not answered yet."""
        return any(e.source is _Own.MODES for e in self._inflight)

    def next_deadline(self) -> float | None:
        if self._closing_reason is not None:
            return None
        deadline = None  # asked after every step: no list built
        for d in (self._banner_deadline, self._handshake_deadline, self._stopping):
            if d is not None and (deadline is None or d < deadline):
                deadline = d
        if self._occupied is not None and (deadline is None or self._next_poll < deadline):
            deadline = self._next_poll  # the polls of a board found busy (`_connecting_report`)
        if self.phase is Phase.READY:
            asked = self._asked_at
            poll = self._next_poll if asked is None else asked + self.heartbeat
            if deadline is None or poll < deadline:
                deadline = poll
            if len(self._silent_asks) >= SILENT_QUERIES:  # `_lost_at` is None before
                lost = self._lost_at()
                if lost is not None and lost < deadline:
                    deadline = lost
        return deadline

    def tick(self) -> None:
        now = self.clock()
        if self._closing_reason is not None:
            return
        if self._handshake_deadline is not None and now >= self._handshake_deadline:
            step = "banner nor answer to $I" if self.flavour is None else "answers to $I, $$, $G, ?"
            self._closing(f"no grbl {step} within {self.handshake_timeout:g} s")
            return
        if self._banner_deadline is not None and now >= self._banner_deadline:
            self._ask_build()  # grblHAL on native USB prints no banner when a port opens
        if self._stopping is not None and now >= self._stopping:
            self._stop_reset(timed_out=True)
        if self.phase is not Phase.READY:
            if self._occupied is not None and now >= self._next_poll:
                self._ask_report()
            return
        lost = self._lost_at()
        if lost is not None and now >= lost:
            moving = self._may_be_moving()
            self._closing(
                f"controller silent for {now - self._heard_at:.1f} s: not a byte, and "
                f"{len(self._silent_asks)} status requests unanswered"
                + (" (it may be moving: the port is not reopened on its own)" if moving else ""),
                reopen=not moving,
            )
        elif self._asked_at is None:
            if now >= self._next_poll:
                self._ask_report()
        elif now >= self._asked_at + self.heartbeat:
            self._ask_report()  # the `?` or its report may have been lost: ask again

    def _silence_allowed(self) -> float | None:
        """Seconds the board may print nothing; None: however long (a homing cycle unbounded)."""
        allowed = self.link_silence
        # classic grbl writes before it answers; grblHAL answers, then writes once idle.
        if self._storing is not None or self._heard_at == self._stored_at:
            allowed += STORAGE_QUIET
        if self._homing_lines or self.model.state is MachineState.HOMING:
            bound = self.homing_timeout
            if bound is None:
                bound = homing_time_bound(self.settings)
            if bound is None:
                return None
            allowed = max(allowed, bound)
        return allowed

    def _lost_at(self) -> float | None:
        """When the link is given up if the board stays silent: its silence has lasted what
        is allowed, and SILENT_QUERIES `?`s went unanswered, the last given `heartbeat`."""
        allowed = self._silence_allowed()
        if allowed is None or len(self._silent_asks) < SILENT_QUERIES:
            return None
        last = self._silent_asks[SILENT_QUERIES - 1]
        return max(self._heard_at + allowed, last + self.heartbeat)

    def _may_be_moving(self) -> bool:
        """Not known to stand still: a reopen (an Arduino's reset) could stop it mid-motion."""
        state = self.model.state
        still = state is not None and (state.is_resting or state.is_lockout)
        planner_empty = (
            self._reports.planner_free is None or self._reports.planner_free >= self.blocks
        )
        return not (still and planner_empty) or bool(self._inflight) or self._homing_lines > 0
