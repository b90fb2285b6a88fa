"""G2Session's lowest layer: the session's state, declared once, and its books.

`G2Session` (g2core.py) is one class written in layers, a file each; this is
the lowest. Every field the session keeps is declared here, once (`__init__`),
so a reader of any layer above finds what `self.` holds in one place. The
books are the lines written and not yet answered (`LineModeSender`,
linemode.py): a line is booked as it is written (`_book`); a line of the
session's own (`_Own`) goes ahead of anything queued (`_ask_own`); a line the
board will never answer is settled here (`_settle_unanswered`).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Iterable
from enum import Enum, auto
from typing import Any

from hostd.protocol.commands import Realtime, encode_get
from hostd.protocol.errors import MachineError
from hostd.protocol.g2builds import NEWEST, Build
from hostd.protocol.g2words import G2Words
from hostd.protocol.linemode import InFlight, LineModeSender, SenderError
from hostd.protocol.session import SessionBase
from hostd.protocol.states import MachineState
from hostd.protocol.vocabulary import Lane, OwnLine, Phase


class _Own(OwnLine, Enum):
    """What a line of the session's own is for; its answer goes back to that."""

    VERSION = auto()  # {fv:n,fb:n}: a board that printed no banner
    SETTING = auto()  # a protocol setting of the handshake
    HOMED = auto()  # {home:n}, in the handshake and after homing
    FIRST_REPORT = auto()  # the handshake's last step: a full status report
    HEARTBEAT = auto()  # a silent board asked for a report
    QUERY = auto()  # a status report asked for (after an `er`, at a job's end)
    REAPPLY = auto()  # a setting sent again once a lockout ended
    CLEAR = auto()  # the clear that ends the ALARM a 100.x board makes of a ^D
    FENCE = auto()  # `{"stat":null}` behind a ^D on the control port: that ^D was read
    OVERRIDES = auto()  # the override factors, read or written (g2builds.py override_keys)
    SPINDLE = auto()  # the handshake asks which spindle keys the board has (g2handshake.py)


class G2Books(G2Words, SessionBase):
    """The session's state and its books of the lines written (see `G2Session`)."""

    def __init__(
        self,
        machine_id: str,
        *,
        window: int = 4,
        status_interval: float = 0.25,
        heartbeat: float = 2.0,
        handshake_timeout: float = 5.0,
        signal_keys: Iterable[str] = (),
        dual: bool = False,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(machine_id, clock)
        # Two ports (g2core.md section 9): a kill or a flush on the control port flushes
        # only that port's input (xio.cpp flushToCommand), so each is sent on both.
        self.dual = dual
        self.build: Build = NEWEST  # the board's rules (g2builds.py), from its `fb`
        self.status_interval = status_interval
        self.heartbeat = heartbeat
        self.handshake_timeout = handshake_timeout
        self.signal_keys = tuple(signal_keys)
        self.sender = LineModeSender(window)
        self._flush: Realtime | None = None  # QUEUE_FLUSH or JOB_KILL, awaiting its proof
        self._flush_out = False  # the flush's byte has been handed to the engine to write
        self._flush_deadline: float | None = None
        # ^D written whose `er` 207 may still come: a 207 of ours is no new exception.
        # Kills that meet merge into one 207, so this only recognises them; the fence
        # behind each ^D (`_write_fence`) is what shows its flush.
        self._kills_unseen = 0
        self._control_fences = 0  # `_Own.FENCE` lines unanswered (two ports)
        self._kill_alarm = False  # a 100.x ^D written: its `er` 207 is an ALARM of ours
        # A lockout an exception report announced: it stands until a report shows the
        # board in it (2, 12, 13) or a clear succeeds, whatever stat a hold shows meanwhile.
        self._held: MachineState | None = None
        self._alarm_kill_due = False  # 101.05+: the alarm's own job kill (`er` 207) is to come
        self._settings_pending = False  # refused in a lockout: sent again when it ends
        self._lines_in = 0  # lines read and understood this connection (the serial fault's value)
        self._last_rx = 0.0
        # The handshake: its deadlines, what it learnt, the settings still to send.
        self._rebooting = False
        self._banner_deadline: float | None = None
        self._handshake_deadline: float | None = None
        self._identity: float | None = None
        self._to_set: deque[dict[str, Any]] = deque()
        # The spindle's keys still to ask for, and the set the board has (SPINDLE_KEYS).
        self._spindle_asks: deque[tuple[str, ...]] = deque()
        self.spindle_keys: tuple[str, ...] = ()
        self._heartbeat_deadline: float | None = None  # a heartbeat query is unanswered
        # Where the board last rested (its machine position, or work position), and whether a report
        # since showed it elsewhere or moving: a stop that moved nothing is no underflow.
        self._rest_at: dict[str, float] | None = None
        self._moved = False
        # `line` and `vel` as the board's automatic reports last said them: what a filtered
        # report leaves out is unchanged since then (report.cpp:480), whatever an answer to
        # `{"sr":null}` said in between (it leaves that record alone, :385).
        self._auto_sr: dict[str, Any] = {}

    # -- the books -------------------------------------------------------------

    def _book(self, encoded: bytes, source: Any, lane: Lane, *, own: bool = False) -> None:
        """Write one line and put it on the books; an urgent one may pass its budget."""
        if self.halted:
            self._settle(source, self._write_refused())
            return
        try:
            self.sender.sent(InFlight(encoded, source, None, own), urgent=own)
        except SenderError as exc:
            self.halt(str(exc))
            self._settle(source, self._write_refused())
            return
        self._out.append((lane, encoded))

    def _ask_own(self, encoded: bytes, purpose: _Own) -> None:
        """A line of the session's own, ahead of anything queued."""
        if self.phase is not Phase.CLOSED:
            self._book(encoded, purpose, Lane.CONTROL, own=True)

    def _query_status(self) -> None:
        """Ask for a full status report, ahead of anything queued."""
        self._ask_own(encode_get("sr"), _Own.QUERY)

    def _settle_unanswered(self, entry: InFlight, error: MachineError) -> None:
        source = entry.source
        if entry.file_line is not None:
            source.discarded += 1
        elif isinstance(source, _Own):
            if source is _Own.HEARTBEAT:
                self._heartbeat_deadline = None  # it was read: the board lives
        else:
            self._settle(source, error)

    def no_data_in_flight(self) -> bool:
        return not self.sender.data_in_flight

    def unanswered(self) -> int:
        return len(self.sender)
