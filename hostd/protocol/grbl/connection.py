"""GrblSession's connection: open, close and the handshake's steps.

A layer of `GrblSession` (session.py). A port opened waits for the banner
(BANNER_WAIT: an Arduino's bootloader runs first; a native USB port prints
none), then asks `$I` with a `?`, then `$$`, `$N`, `$G` and a first report
(`_ask_build`, `_own_answered`), and is ready (`_ready`). A board found
running or holding moves it had before (`_connecting_report`) answers the `?`
but parses no line until they end: the handshake waits for it, polling, and
says so (`Occupied`). A close settles every line the board held and forgets
what the link knew.
"""

from __future__ import annotations

from hostd.protocol.errors import NotConnected
from hostd.protocol.grbl import codec
from hostd.protocol.grbl.books import _Own
from hostd.protocol.grbl.codes import IDLE_ERROR
from hostd.protocol.grbl.report import ReportReader
from hostd.protocol.grbl.stops import GrblStops
from hostd.protocol.messages import Response
from hostd.protocol.vocabulary import Excepted, Occupied, Phase, Ready

BANNER_WAIT = 2.0  # s: an Arduino's bootloader runs ~1.5 s before grbl prints its banner

# The states in which grbl's main loop parses the lines it is sent (gnea/grbl protocol.c:
# protocol_main_loop; a Hold, a Door, a cycle or a jog keep it in protocol_execute_realtime
# or in a planner wait, in which only realtime characters act). Idle with a full receive
# buffer, dropping bytes, is not told apart: it empties within a pass.
_READING = frozenset({"Idle", "Alarm", "Check", "Sleep"})


class GrblConnection(GrblStops):
    """The link's opening, handshake and closing (see `GrblSession`)."""

    def open(self, *, rebooting: bool = False) -> None:
        now = self.clock()
        self.phase = Phase.HANDSHAKE
        self._closing_reason = None
        self._resync = self._asked_build = self._first_report = False
        self._build_refused = False
        self._occupied = None
        self._stale_answers = 0
        self._handshake_deadline = now + self.handshake_timeout
        wait = min(BANNER_WAIT, self.handshake_timeout / 2)
        self._banner_deadline = None if rebooting else now + wait

    def close(self, reason: str, *, restarted: bool = False) -> None:
        self.phase = Phase.CLOSED
        self._reports = ReportReader()  # the next connection's reports say WCO anew
        self._banner_deadline = self._handshake_deadline = self._stopping = None
        self._resetting = False
        self._held = self._occupied = None
        self._forget_holds()
        self._override = None  # machine.override sees the link go down
        self._forget(NotConnected(f"link lost: {reason}"))
        self._end_stream_on_close(reason, restarted)
        self._out.clear()
        self._lines_in = 0
        self.model.reset()

    def _own_answered(self, own: _Own, response: Response) -> None:
        if (
            response.status == IDLE_ERROR
            and own in (_Own.BUILD, _Own.SETTINGS, _Own.STARTUP)
            and self.phase is Phase.HANDSHAKE
            and not self._resync
        ):
            # Busy: `$I` and `$N` are refused outside Idle and Alarm (gnea/grbl system.c:
            # 172-175; grblHAL core system.c:635 and :726), `$$` in a cycle or a hold
            # (:309; gnea/grbl :140). Asked again, from `$I`, once a report shows it at rest.
            self._build_refused = True
            self._ask_report()
            return
        if own is _Own.BUILD:
            self._ask_own("$$", _Own.SETTINGS)
        elif own is _Own.SETTINGS:
            self._ask_own("$N", _Own.STARTUP)
        elif own is _Own.STARTUP:
            self._ask_own("$G", _Own.MODES)
        elif own is _Own.MODES and self.phase is Phase.HANDSHAKE:
            self._first_report = True
            self._ask_report()

    def _ask_build(self) -> None:
        """`$I`, once: after the banner, or when none came; and a `?`, which a board busy
        with moves of before answers although `$I` waits behind them
        (`_connecting_report`)."""
        self._banner_deadline = None
        if not self._asked_build:
            self._asked_build = True
            self._ask_own("$I", _Own.BUILD)
            self._ask_report()

    def _connecting_report(self, report: codec.StatusReport) -> None:
        """A report before the handshake's lines are answered: the board may be running or
        holding moves it was given before this link (a daemon that died mid-job, a job
        from its own SD card). It parses no line until they end (`_READING`), so `$I`
        is not answered, maybe for minutes: the handshake waits for as long as the
        board answers its `?`s, polls it (the status topic shows it move), and says so
        once a state (`Occupied`). Not closed and reopened on a timeout: an Arduino
        resets when its port opens, mid-motion."""
        now = self.clock()
        if report.state in _READING:
            if self._occupied is not None:
                self._occupied = None  # it reads again: `$I` is answered now, or never
                self._handshake_deadline = now + self.handshake_timeout
            if self._build_refused:
                self._build_refused = self._asked_build = False
                self._ask_build()
            return
        self._handshake_deadline = now + self.handshake_timeout  # it lives: wait on
        self._next_poll = now + self.status_interval
        state = report.state  # Hold:1 then Hold:0 is one hold: told once
        if state == self._occupied:
            return
        self._occupied = state
        if state == "Door":
            message = (
                f"{self.id} is in Door: its safety door is open, or was opened, and it reads "
                "no command until the door is closed and machine.cycle_start resumes it "
                "(it runs on with any moves it holds; machine.reset drops them). hostd "
                "connects then"
            )
        else:
            message = (
                f"{self.id} is {state}, busy with moves it was given before this "
                "connection: hostd connects once they end. machine.feedhold holds it; "
                "machine.reset empties it"
            )
        self._job_log().warning("board busy with moves of before", state=state)
        told = {"msg": message, "state": state}
        self.model.last_exception = told
        self._events.append(Excepted(told))
        self._events.append(Occupied(state, message))

    def occupied(self) -> dict[str, str] | None:
        state = self._occupied
        if state is None:
            return None
        exception = self.model.last_exception or {}
        return {"state": state, "message": str(exception.get("msg") or state)}

    def _restart_handshake(self) -> None:
        """Our reset before the handshake was through: the board emptied its input, the
        `$I` with it (gnea/grbl main.c: serial_reset_read_buffer). Ask anew."""
        self._resetting = False
        self._forget(NotConnected("not answered: discarded by the controller's reset"))
        self._asked_build = self._first_report = self._build_refused = False
        self._occupied = None
        self._handshake_deadline = self.clock() + self.handshake_timeout
        self._ask_build()

    def _ready(self) -> None:
        self.phase = Phase.READY
        self._handshake_deadline = None
        self._resync = self._first_report = False
        self._occupied = None
        now = self.clock()
        self._next_poll = now + self.status_interval
        self._heard_at = now
        self._silent_asks.clear()
        self._events.append(Ready())
