"""GrblSession's lowest layer: the session's state, declared once, and its books.

`GrblSession` (session.py) is one class written in layers, a file each; this
is the lowest. Every field the session keeps is declared here, once
(`__init__`), so a reader of any layer above finds what `self.` holds in one
place. The books are the lines written and not yet answered, in order, and
the bytes of them in the board's receive buffer (`_rx_used`): a line is
booked as it is written (`_book`); a homing line, or one that writes EEPROM
or flash (`$x=`, `$I=`, `$Nx=`, `$RST=`, G10 L2/L20, G28.1, G30.1: codec.py),
is marked as such (`_special`); a line of the session's own (`_Own`) goes at
once (`_ask_own`); a `?` is asked (`_ask_report`); and when the board forgets
every line it held (a reset, a lost link) each is settled (`_forget`). Here
too the command class table grbl admits lines by (`ADMISSION`).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from enum import Enum, auto
from typing import TYPE_CHECKING, Any

from hostd.protocol.classes import FORWARD, CommandClass, Table, admit
from hostd.protocol.errors import MachineError
from hostd.protocol.grbl import codec
from hostd.protocol.grbl.report import ReportReader
from hostd.protocol.grbl.words import GrblWords
from hostd.protocol.linemode import InFlight
from hostd.protocol.session import SessionBase
from hostd.protocol.states import MachineState
from hostd.protocol.status import Status
from hostd.protocol.vocabulary import Lane, OwnLine, Phase

if TYPE_CHECKING:
    from hostd.protocol.grbl.overrides import _Rounds

SILENT_QUERIES = 3  # `?`s unanswered in a silence before the link is given up

_REFUSED_BY_ALARM = Status.COMMAND_REJECTED_BY_ALARM
_REFUSED_BY_SHUTDOWN = Status.COMMAND_REJECTED_BY_SHUTDOWN
_REFUSED_BY_PANIC = Status.COMMAND_REJECTED_BY_PANIC

# g2core's table but for two rows: M2/M30 do not clear a grbl alarm (they are
# actions), and `$X`/`$H` do not leave an e-stop or Sleep (a reset does).
ADMISSION: Table = {
    CommandClass.QUERY: (FORWARD, FORWARD, FORWARD),
    CommandClass.CLEAR: (FORWARD, _REFUSED_BY_SHUTDOWN, _REFUSED_BY_PANIC),
    CommandClass.PROGRAM_END: (_REFUSED_BY_ALARM, _REFUSED_BY_SHUTDOWN, _REFUSED_BY_PANIC),
    CommandClass.RESET: (FORWARD, FORWARD, FORWARD),
    CommandClass.HALT: (FORWARD, FORWARD, FORWARD),
    CommandClass.ACTION: (_REFUSED_BY_ALARM, _REFUSED_BY_SHUTDOWN, _REFUSED_BY_PANIC),
}


class _Own(OwnLine, Enum):
    BUILD = auto()  # $I: [VER:...] and [OPT:...,blocks,rx]
    SETTINGS = auto()  # $$: laser mode ($32)
    STARTUP = auto()  # $N: the startup blocks the board runs at every reset
    MODES = auto()  # $G: [GC:...]


class GrblBooks(GrblWords, SessionBase):
    """The session's fields and its books (see `GrblSession`)."""

    def __init__(
        self,
        machine_id: str,
        *,
        status_interval: float = 0.25,
        heartbeat: float = 2.0,
        link_silence: float = 10.0,
        homing_timeout: float | None = None,
        handshake_timeout: float = 5.0,
        startup_motion: bool = False,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(machine_id, clock)
        # A startup block that moves runs at every reset: unless the config allows it,
        # a stop holds the board instead of resetting it (`_held`, docs/dialects.md).
        self.startup_motion = startup_motion
        self._held: str | None = None
        self.status_interval = status_interval
        self.heartbeat = heartbeat  # a `?` unanswered this long is asked again
        self.link_silence = link_silence  # s without a byte (and SILENT_QUERIES `?`): gone
        self.homing_timeout = homing_timeout  # None: the bound the settings give
        self.handshake_timeout = handshake_timeout
        self.flavour: str | None = None  # "Grbl" or "GrblHAL", as its banner or `$I` says
        self.version: str | None = None
        self.rx_size = codec.CLASSIC_RX_BUFFER
        self.blocks = codec.CLASSIC_BLOCKS
        # `[OPT:]` says `N`: the board keeps a line's N word and reports it (`Ln:`).
        # None until `$I` is read (a board that never says: lines are numbered).
        self.line_numbers: bool | None = None
        self.settings: dict[str, str] = {}
        self._inflight: deque[InFlight] = deque()  # written, unanswered, in order
        self._rx_used = 0  # bytes of them: never more than the board's buffer holds
        self._said: list[str] = []  # what the board printed for the line it is answering
        self._report_waiters: list[Any] = []  # clients' `?`: answered by the next report
        self._reports = ReportReader()  # what reports said now and then (WCO)
        self._asked_at: float | None = None  # the last `?`, while no report has answered it
        # When each `?` no report has answered yet was written (`asks_open`); a report
        # takes off the newest (grbl answers the `?`s one pass reads with one report, so
        # one may never be answered: those older than `link_silence` are dropped).
        self._asks: deque[float] = deque()
        self._next_poll = 0.0
        self._heard_at = 0.0  # the last line the board printed, whatever it was
        self._silent_asks: list[float] = []  # the first `?`s written since then
        self._homing_lines = 0  # `$H` lines unanswered: the board may be homing
        self._homing_failed = False  # an ALARM came while a `$H` was unanswered
        # The last ALARM, `ALARM:9 (text)`, while no answer has come since: what a reset
        # the board makes itself right after it (a failed homing, a limit) is told with.
        self._alarm_unanswered: str | None = None
        self._storing: InFlight | None = None  # a line writing EEPROM or flash, unanswered
        self._stored_at: float | None = None  # when the last such line was answered
        self._stopping: float | None = None  # a feedhold waiting for rest, until then
        # Reports read after a stop's `!` that may still predate it, and so say nothing of
        # its rest (`_begin_stop`): the answers to older `?`s, and on grblHAL one unasked.
        self._stop_skips = 0
        # A `!` of ours written, and no report since shows its hold complete (Hold:0) or
        # the board out of motion: a `~` now would be dropped (`_realtime`).
        self._hold_settling = False
        self._start_pending = False  # a `~` kept back until the hold completes
        self._resume_asks = 0  # `?`s left to ask while reports say Hold after our `~`
        self._override: _Rounds | None = None  # machine.override, not yet answered
        self._resetting = False  # 0x18 written: the banner is next
        self._needs_reset: int | None = None  # a critical alarm: no line until a reset
        self._resync = False  # the handshake after a reset: only `$G` and a report
        self._asked_build = False  # the handshake asked `$I`
        self._occupied: str | None = None  # the busy state the board was found in (Occupied)
        self._build_refused = False  # a handshake line answered error:8: `$I` again at rest
        self._stale_answers = 0  # `ok`s of before this link, dropped while connecting
        self._first_report = False  # the handshake waits for its first report
        self._banner_deadline: float | None = None
        self._handshake_deadline: float | None = None
        self._lines_in = 0

    def _admit(self, cls: CommandClass, state: MachineState | None) -> int | None:
        return admit(cls, state, ADMISSION)

    def flushing(self) -> bool:
        return self._stopping is not None or self._resetting or self._held is not None

    def no_data_in_flight(self) -> bool:
        return not self._inflight

    def unanswered(self) -> int:
        return len(self._inflight)

    def _book(self, encoded: bytes, source: Any) -> None:
        entry = InFlight(encoded, source, None, isinstance(source, _Own))
        self._inflight.append(entry)
        self._rx_used += len(encoded)
        self._out.append((Lane.DATA, encoded))
        self._special(entry)

    def _special(self, entry: InFlight) -> bool:
        """Book a homing or storing line; True if nothing may be written after it yet."""
        line = entry.line
        if line[:1] == b"$":
            if codec.homes(line):
                self._homing_lines += 1
        elif not _MAY_STORE(line):
            return False  # a job's line, almost always: one regex search
        if codec.stores(line):
            self._storing = entry
            return True
        return False

    def _ask_own(self, text: str, purpose: _Own) -> None:
        """A line of the session's own: it goes now, budget or not (they are few and short)."""
        if self.phase is not Phase.CLOSED:
            self._book(codec.encode(text), purpose)

    def _ask_report(self) -> None:
        now = self.clock()
        self._asked_at = now
        asks = self._asks
        if asks and asks[0] < now - self.link_silence:
            asks.popleft()  # never answered (see `_asks_open`); one a `?` keeps it short
        asks.append(now)
        self._next_poll = now + self.status_interval
        if len(self._silent_asks) < SILENT_QUERIES:
            self._silent_asks.append(now)
        self._out.append((Lane.REALTIME, codec.STATUS))

    def _asks_open(self) -> int:
        """`?`s written that may still be answered, each by a report of its own: a board
        that reads its input in order and slowly (grblHAL's upstream Simulator feeds its
        firmware a byte a main-loop pass, behind the lines before it) answers the
        `?`s the heartbeat asked again one by one, long after they were written."""
        asks, oldest = self._asks, self.clock() - self.link_silence
        while asks and asks[0] < oldest:
            asks.popleft()
        return len(asks)

    def _query_status(self) -> None:
        if self.phase is not Phase.CLOSED:
            self._ask_report()

    def _forget(self, error: MachineError) -> None:
        """Every line the board held is gone (a reset, a lost link): settle each."""
        for entry in self._inflight:
            self._settle_lost(entry, error)
        self._inflight.clear()
        self._rx_used = 0
        self._said.clear()
        for waiting in (self._outbox, self._lane):
            while waiting:
                self._settle(waiting.popleft().token, error)
        for token in self._report_waiters:
            self._settle(token, error)
        self._report_waiters.clear()
        self._await_report = self._awaiting_rest = False
        self._asked_at = None
        self._asks.clear()
        self._homing_lines = 0
        self._homing_failed = False
        self._storing = None

    def _settle_lost(self, entry: InFlight, error: MachineError) -> None:
        if entry.file_line is not None:
            entry.source.discarded += 1
        else:
            self._settle(entry.source, error)


_MAY_STORE = codec.MAY_STORE.search
