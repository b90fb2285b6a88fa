"""GrblSession's connection: open, close and the handshake's steps.

A layer of `GrblSession` (session.py). A port opened waits for the banner
(BANNER_WAIT: an Arduino's bootloader runs first; a native USB port prints
none), then asks `$I`, `$$`, `$N`, `$G` and a first report (`_ask_build`,
`_own_answered`), and is ready (`_ready`). A close settles every line the
board held and forgets what the link knew.
"""

from __future__ import annotations

from hostd.protocol.errors import NotConnected
from hostd.protocol.grbl.books import _Own
from hostd.protocol.grbl.report import ReportReader
from hostd.protocol.grbl.stops import GrblStops
from hostd.protocol.messages import Response
from hostd.protocol.vocabulary import Phase, Ready

BANNER_WAIT = 2.0  # s: an Arduino's bootloader runs ~1.5 s before grbl prints its banner


class GrblConnection(GrblStops):
    """The link's opening, handshake and closing (see `GrblSession`)."""

    def open(self, *, rebooting: bool = False) -> None:
        now = self.clock()
        self.phase = Phase.HANDSHAKE
        self._closing_reason = None
        self._resync = self._asked_build = self._first_report = False
        self._handshake_deadline = now + self.handshake_timeout
        wait = min(BANNER_WAIT, self.handshake_timeout / 2)
        self._banner_deadline = None if rebooting else now + wait

    def close(self, reason: str, *, restarted: bool = False) -> None:
        self.phase = Phase.CLOSED
        self._reports = ReportReader()  # the next connection's reports say WCO anew
        self._banner_deadline = self._handshake_deadline = self._stopping = None
        self._resetting = False
        self._held = None
        self._forget_holds()
        self._override = None  # machine.override sees the link go down
        self._forget(NotConnected(f"link lost: {reason}"))
        self._end_stream_on_close(reason, restarted)
        self._out.clear()
        self._lines_in = 0
        self.model.reset()

    def _own_answered(self, own: _Own, response: Response) -> None:
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
        """`$I`, once: after the banner, or when none came."""
        self._banner_deadline = None
        if not self._asked_build:
            self._asked_build = True
            self._ask_own("$I", _Own.BUILD)

    def _ready(self) -> None:
        self.phase = Phase.READY
        self._handshake_deadline = None
        self._resync = self._first_report = False
        now = self.clock()
        self._next_poll = now + self.status_interval
        self._heard_at = now
        self._silent_asks.clear()
        self._events.append(Ready())
