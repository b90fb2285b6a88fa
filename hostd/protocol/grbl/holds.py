"""GrblSession's holds and resumes: a `~` that is not lost, and a resume seen soon.

A layer of `GrblSession` (session.py). grbl drops a cycle start read while a
hold still decelerates, and answers a `?` read with a `!` or a `~` before it
acts on it (protocol.c): so after our `!` the session polls soon
(`_poll_soon`, SETTLE_POLL) until a report shows the hold complete, and only
then writes a `~` kept back (`_hold_settled`); after a `~` it asks again while
reports still say Hold (`_cycle_start`, `_resume_seen`, RESUME_ASKS). A reset
or a closed link forgets both (`_forget_holds`).
"""

from __future__ import annotations

from hostd.protocol.grbl import codec
from hostd.protocol.grbl.flow import GrblFlow
from hostd.protocol.vocabulary import Lane

# s from our `!` to the next `?`, and between `?`s until the hold is complete: a report
# read with the `!` predates it (protocol.c), and a `~` kept back waits for Hold:0.
SETTLE_POLL = 0.02
RESUME_ASKS = 3  # `?`s after a `~` while reports still say Hold (`_cycle_start`)


class GrblHolds(GrblFlow):
    """Our holds' settling and our resumes (see `GrblSession`)."""

    def _hold_settled(self, report: codec.StatusReport) -> None:
        """A report after our `!`: once it shows no motion still stopping, a `~` kept
        back goes (Hold:0, Idle), or is dropped (a door, an alarm: the operator decides
        again there). A report of Run may predate the `!` (read in the same pass)."""
        if report.state in ("Run", "Jog", "Home") or (report.state == "Hold" and report.sub == 1):
            return
        self._hold_settling = False
        if self._start_pending:
            self._start_pending = False
            if report.state in ("Hold", "Idle"):
                self._cycle_start()
            else:
                self._job_log().warning("resume dropped", board_state=self.model.board_state)

    def _cycle_start(self) -> None:
        """`~`, with a `?` behind it: a job's lines wait while the last report says Hold.

        grbl answers a `?` read with the `~` before it acts on the `~` (protocol.c
        protocol_exec_rt_system: EXEC_STATUS_REPORT is handled before EXEC_CYCLE_START;
        grblHAL the same, reporting before `state_update`), so that report still says
        Hold: `_on_report` asks again while one does, up to RESUME_ASKS times. Without
        the asks the job's lines waited for the next poll, `status_interval` away, while
        the board ran its planner dry (docs/dialects.md, the Holds row).
        """
        self._out.append((Lane.REALTIME, codec.CYCLE_START))
        self._resume_asks = RESUME_ASKS
        self._ask_report()

    def _poll_soon(self, within: float = SETTLE_POLL) -> None:
        """The next `?` within `within` (SETTLE_POLL), not a `status_interval` away."""
        self._next_poll = min(self._next_poll, self.clock() + within)

    def _forget_holds(self) -> None:
        """A reset or a closed link: no hold of ours settles, no resume is kept."""
        self._hold_settling = self._start_pending = False
        self._resume_asks = 0

    def _resume_seen(self, report: codec.StatusReport) -> None:
        """A report after our `~`: one that still says Hold predates it; ask again."""
        if report.state == "Hold":
            self._resume_asks -= 1
            if self._resume_asks:
                self._ask_report()
        else:
            self._resume_asks = 0
