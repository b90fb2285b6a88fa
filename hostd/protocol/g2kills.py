"""G2Session's kills and flushes: the realtime controls, and the proof of each flush.

A layer of `G2Session` (g2core.py). A realtime control goes on the realtime
lane (`_write_realtime`). After `%` or 0x04 no data line is written until the
board shows the flush happened; then the lines it discarded are taken off the
books and accounted. A `%` is shown by a stop (stat 3/4, `_confirm_flush`); a
^D by its fences (`_write_fence`, `_kill_fenced`; docs/protocol.md, "A kill's
fence"). After `FLUSH_CONFIRM_TIMEOUT` with no proof the wait ends (`tick`,
g2connection.py). Before 101.02 a ^D is an ALARM that flushes nothing
(g2builds.py `kill_alarms`). The `er` 207 a kill brings is read with the
lockouts (g2lockouts.py `_on_kill_report`): what it means depends on them.
"""

from __future__ import annotations

from hostd.protocol.commands import Realtime, encode_get, encode_realtime
from hostd.protocol.errors import ControllerError, MachineError
from hostd.protocol.g2books import _Own
from hostd.protocol.g2flow import G2Flow
from hostd.protocol.linemode import InFlight
from hostd.protocol.states import MachineState
from hostd.protocol.status import Status
from hostd.protocol.vocabulary import Lane, StreamEnd

FLUSH_CONFIRM_TIMEOUT = 2.0

# States in which the board has run its flush (cycle ended, planner empty).
_FLUSH_CONFIRMED = frozenset({MachineState.PROGRAM_STOP, MachineState.PROGRAM_END})


class G2Kills(G2Flow):
    """Kills, flushes and the other realtime controls (see `G2Session`)."""

    # -- realtime controls -----------------------------------------------------

    def _realtime(self, command: Realtime) -> None:
        self._write_realtime(command)

    def reset(self) -> None:
        """0x18: the board reboots; so do the session's books when it comes back."""
        self._require_open()
        self._write_realtime(Realtime.RESET)
        self.halted = False

    def _stop_board(self) -> None:
        """A fault's stop: feedhold, then flush what the board holds."""
        self._write_realtime(Realtime.FEEDHOLD)
        self._write_realtime(Realtime.QUEUE_FLUSH)

    def _write_realtime(self, command: Realtime) -> None:
        self._out.append((Lane.REALTIME, encode_realtime(command)))
        build = self.build
        if command is Realtime.JOB_KILL and build.kill_alarms:
            # Before 101.02 ^D is an ALARM and flushes nothing: every line in flight is
            # read and answered 204, and those answers settle it (g2builds.py).
            self._kill_alarm = True
            if self.stream is not None:
                self._end_stream(self.stream, StreamEnd.CANCELLED, None, "job killed")
            return
        if command is Realtime.JOB_KILL:
            self._kills_unseen += 1
            if self.dual:  # the data port's lines too: the ^D flushes its own port only
                self._out.append((Lane.DATA, encode_realtime(command)))
                self._kills_unseen += 1
            self._write_fence()
        elif (
            command is Realtime.QUEUE_FLUSH and self.dual and not build.flush_reads_every_data_port
        ):
            # Before 101.05 a `%` flushes its own port alone; after a `!` on the same
            # port it is a flush even at rest (xio.cpp `_last_control_was_feedhold`).
            self._out.append((Lane.DATA, encode_realtime(Realtime.FEEDHOLD)))
            self._out.append((Lane.DATA, encode_realtime(command)))
        if command in (Realtime.QUEUE_FLUSH, Realtime.JOB_KILL):
            # Whether the board flushes depends on its state *now*, which the last
            # report may not show yet: expect a flush, and let the confirmation
            # (or its absence) decide what happened to the lines in flight.
            self._begin_flush(command)

    # -- kills -----------------------------------------------------------------

    def _write_fence(self) -> None:
        """The fences behind a ^D (docs/protocol.md, "A kill's fence").

        On the data port (the only port, or the second) `$stat`, a data line: the
        board reads that port's controls first, each in turn, and its data lines in
        order (xio.cpp:643-827); the ^D it reads throws away the data lines it had
        scanned, those written before the ^D (controller.cpp:282, xio.cpp:984-1017),
        in any state; and no data line is read while a hold is on (cycle_feedhold.cpp
        :325), so not before the kill's own hold has ended in its kill. When `$stat`
        is answered, each data line written before it was answered already or is
        gone, and the kill has run. A GET of a read-only status key (`_FENCE_KEYS`)
        is answered in any state; as `$stat` it takes a form no other line does (a
        client's query goes as strict JSON, `_as_json_query`, and a SET of a
        read-only key is answered with an error).

        On two ports also `{"stat":null}` behind the control port's ^D, in that
        port's order: answered, that ^D was read, so no kill of hostd's can reach
        the board later and stop what runs then.
        """
        if self.halted:
            return  # nothing is written: the link is being torn down
        # A fence still unanswered may be thrown away unread by this ^D: each asks for
        # another key, so that its answer says which it is (LineModeSender.fence).
        in_use = self.sender.fence_keys()
        key = next((k for k in _FENCE_KEYS if frozenset((k,)) not in in_use), None)
        if key is None:
            # As many kills at once as keys (a board that read none of their fences):
            # no fence. The timeout ends the wait; lines still booked stay booked until
            # an earlier fence, if any is still read, settles them.
            self._log.warning("no fence for a kill: too many kills at once", kills=len(in_use))
        else:
            fence = f"${key}\n".encode("ascii")
            self.sender.fence(InFlight(fence, _Own.FENCE, None, True), frozenset((key,)))
            self._out.append((Lane.DATA, fence))
        if self.dual:
            self._control_fences += 1
            self._book(encode_get("stat"), _Own.FENCE, Lane.CONTROL, own=True)

    def _kill_fenced(self) -> None:
        """A fence was answered: with the last of every kill's, the kills' wait ends.

        Every ^D was read by then and every kill it asked for has run: its `er`
        207, if any, came first (`_run_job_kill` runs before the next line is read
        at rest, and ends the hold the data port waits for in a cycle)."""
        if self.sender.fences or self._control_fences:
            return
        self._kills_unseen = 0
        if self._flush is Realtime.JOB_KILL:
            self._flush = self._flush_deadline = None

    # -- flushes ---------------------------------------------------------------

    def _begin_flush(self, kind: Realtime) -> None:
        self._flush = kind
        self._flush_out = False
        self._flush_deadline = self.clock() + FLUSH_CONFIRM_TIMEOUT
        if self.stream is not None and not self.stream.done:
            reason = "job killed" if kind is Realtime.JOB_KILL else "queue flushed"
            self._end_stream(self.stream, StreamEnd.CANCELLED, None, reason)

    def _confirm_flush(self) -> None:
        """A queue flush is shown by a stop (stat 3 or 4), read after the `%` went out (a
        report read before then, in the batch that decided the flush, says nothing of
        it): the data lines the board held are dropped from the books. A job kill is
        shown by its fence (`_fence_answered`), not here.
        """
        if self._flush is not Realtime.QUEUE_FLUSH or not (
            self._flush_out and self.model.state in _FLUSH_CONFIRMED
        ):
            return
        self._flush = self._flush_deadline = None
        self._kills_unseen = 0
        for entry in self.sender.dropped():
            self._settle_unanswered(entry, _discarded(Realtime.QUEUE_FLUSH))

    def flushing(self) -> bool:
        return self._flush is not None


# A kill's fence on the data port (`_write_fence`): `$<key>`, a text-mode GET answered
# in JSON (`{"r":{"stat":N},"f":[1,0,6]}`: text_parser.cpp:84-96; `__TEXT_MODE` is on,
# g2core.h:42) of read-only status keys, another for each fence unanswered at once
# (edge-preview canonical_machine.cpp:2409-2420, :2510; 101.03 config_app.cpp:117-153).
_FENCE_KEYS = ("stat", "line", "unit", "vel", "feed", "posx", "posy", "posz")


def _discarded(kind: Realtime) -> MachineError:
    status = Status.KILL_JOB if kind is Realtime.JOB_KILL else Status.NOOP
    what = "job kill" if kind is Realtime.JOB_KILL else "queue flush"
    return ControllerError(int(status), f"discarded by the controller's {what} before it ran")
