"""grbl 1.1's and grblHAL's session: the rules of a one-port, character-counted board.

Sources are cited as grblHAL/core files (protocol.c, report.c, system.c,
stream.h, grbl.h) and the grbl wiki's "Interface" page; docs/dialects.md sets
the rules beside g2core's.

- **Flow control**: character counting. grbl answers every line it takes
  from its receive buffer with `ok` or `error:N`, in order; the host never
  has more unanswered bytes than the buffer holds (a ring of N bytes holds
  N - 1): 128 on classic grbl, what `[OPT:...,blocks,rx]` says on grblHAL.
  An overfilled buffer loses characters.
- **Realtime**: `?`, `!`, `~`, 0x18, 0x85 (jog cancel) are picked out of the
  stream wherever they are (protocol.c); they take no buffer room and get no
  answer. grbl pushes no status: the session asks `?` every
  `status_interval`.
- **Liveness**: every line the board prints says it lives, `ok`s included: a
  board busy answering a job's lines is alive even when its status reports
  stop. A `?` no report answers within `heartbeat` is asked again (one can be
  lost to line noise, or to an AVR's EEPROM write, which turns the serial
  interrupt off). The link is given up only after `link_silence` seconds
  without a byte and at least `SILENT_QUERIES` unanswered `?`s. While a line
  writes EEPROM or flash the board may be deaf for up to 2 s more
  (`STORAGE_QUIET`); while it homes (a `$H` unanswered, or a report saying
  Home) it may be silent for the whole cycle (classic grbl's limits_go_home
  serves no `?`; grblHAL forces one `<Home>` report and then serves none), so
  the silence allowed is then the cycle's bound from its settings
  (`homing_time_bound`) or `homing_timeout`. A board given up while it may be
  moving is not reopened on its own: reopening an Arduino's port resets it.
- **EEPROM and flash writes** (`$x=`, `$I=`, `$Nx=`, `$RST=`, G10 L2/L20,
  G28.1, G30.1) go send-response: nothing more is written until the board
  answers one, as the grbl wiki's "EEPROM Issues" asks, since bytes that
  arrive during the write are lost.
- **Lockouts**: `ALARM:N` puts the board in ALARM; only `$X`, `$H` and 0x18
  reach it (grbl answers anything else `error:9`). An e-stop (ALARM:10), a
  failed self test or a motor fault, and Sleep, are left only by a reset: the
  common SHUTDOWN.
- **Holds**: grbl runs no line inside a hold (lines wait in its buffer), so
  a client's line in a hold, or with the door open, is refused on the host.
- **Stopping** (a cancel, a fault): feedhold, and once motion has stopped (a
  report says Hold:0 or Idle) a soft reset, which empties the board's buffer
  and planner; then a re-sync. A reset during motion loses the position
  (grbl then raises ALARM:3), so the snapshot says `homed` false.
- **Resets**: the board prints its banner again and forgets every line it
  held; the session settles them and re-syncs (`$G`, `?`) on the same link.

How a status report, `[GC:]` and `[PRB:]` map onto the common names is in
report.py.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum, auto
from typing import Any

from hostd.protocol.classes import FORWARD, CommandClass, Table, admit
from hostd.protocol.commands import Realtime
from hostd.protocol.errors import Busy, ControllerError, MachineError, NotConnected, Rejected
from hostd.protocol.grbl import codec
from hostd.protocol.grbl.codes import (
    ALARM_STATE,
    CRITICAL,
    LOCKOUT_ERRORS,
    POSITION_LOST,
    alarm_text,
    error_text,
)
from hostd.protocol.grbl.report import (
    STATES,
    ReportReader,
    apply_modes,
    grbl_named,
    probe_report,
)
from hostd.protocol.grbl.words import GrblWords, homing_time_bound
from hostd.protocol.linemode import InFlight
from hostd.protocol.maintenance import startup_blocks
from hostd.protocol.messages import Response
from hostd.protocol.program import MAX_LINE_NUMBER, NOT_PREFIXED, number_line
from hostd.protocol.session import SessionBase
from hostd.protocol.states import MachineState
from hostd.protocol.status import Status
from hostd.protocol.stream import Stream
from hostd.protocol.vocabulary import (
    Context,
    Excepted,
    Lane,
    OwnLine,
    Phase,
    Probed,
    Queued,
    Ready,
    Reported,
    StreamEnd,
)

# STATES lives in report.py with the rest of the report mapping and stays importable from here.
__all__ = [
    "ADMISSION",
    "BANNER_WAIT",
    "SILENT_QUERIES",
    "STATES",
    "STOP_TIMEOUT",
    "STORAGE_QUIET",
    "GrblSession",
    "homing_time_bound",
]

BANNER_WAIT = 2.0  # s: an Arduino's bootloader runs ~1.5 s before grbl prints its banner
# s from our `!` to the next `?`, and between `?`s until the hold is complete: a report
# read with the `!` predates it (protocol.c), and a `~` kept back waits for Hold:0.
SETTLE_POLL = 0.02
RESUME_ASKS = 3  # `?`s after a `~` while reports still say Hold (`_cycle_start`)
# `?`s more after an override round while a report that postdates its bytes carries no
# `Ov:` and one may be due next (classic grbl defers it a report behind `WCO:`)
OVERRIDE_ASKS = 2
# Override rounds at most (`override`): the first, from a reset to 100, then steps from
# what the board reported. Classic grbl takes one byte of a kind a pass, so a round moves
# a feed or spindle override by one step of ten and one of one: 100 to any of 10..200 is
# at most 10 rounds, and any value to any other at most 19 (190 = 19 steps of ten);
# grblHAL takes 15 a ring a pass (the 19 bytes of 100 to 199 or 11: two rounds).
OVERRIDE_ROUNDS = 20
# grblHAL's override rings (override.h OVERRIDE_BUFSIZE 16, override.c:37-42: a byte
# arriving at a full ring is dropped): 15 usable. Feed and rapid share one (protocol.c:941-950).
OVERRIDE_RING = 15
STOP_TIMEOUT = 2.0  # s for a feedhold to bring motion to rest before the reset goes anyway
SILENT_QUERIES = 3  # `?`s unanswered in a silence before the link is given up
# s of silence allowed on top of `link_silence` while a line writes EEPROM or flash: an
# AVR writes a byte in 3.4 ms with its interrupts off (`$RST=*` rewrites ~1 KB); an STM32
# erases a flash sector in 1-2 s.
STORAGE_QUIET = 2.5

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


@dataclass(slots=True)
class _Rounds:
    """A machine.override under way (`GrblSession.override`): what was asked, and its
    rounds so far."""

    wanted: dict[str, int]  # percent: feed, rapid, spindle, those asked
    rounds: int = 0  # rounds written
    hops: int = 0  # reports to read before one surely postdates the last round's bytes
    asks: int = 0  # `?`s left while such a report carries no `Ov:`
    gap: int | None = None  # how far from `wanted` the last round found the board
    final: bool = False  # the board was reset: the next `Ov:` is the answer

    def gap_to(self, now: dict[str, float]) -> int | None:
        """How far `now` is from the values asked (None: a value was never reported)."""
        if any(what not in now for what in self.wanted):
            return None
        return sum(abs(round(now[what]) - percent) for what, percent in self.wanted.items())


class GrblSession(GrblWords, SessionBase):
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
        self.settings: dict[str, str] = {}
        self._inflight: deque[InFlight] = deque()  # written, unanswered, in order
        self._rx_used = 0  # bytes of them: never more than the board's buffer holds
        self._said: list[str] = []  # what the board printed for the line it is answering
        self._report_waiters: list[Any] = []  # clients' `?`: answered by the next report
        self._reports = ReportReader()  # what reports said now and then (WCO)
        self._asked_at: float | None = None  # the last `?`, while no report has answered it
        self._next_poll = 0.0
        self._heard_at = 0.0  # the last line the board printed, whatever it was
        self._silent_asks: list[float] = []  # the first `?`s written since then
        self._homing_lines = 0  # `$H` lines unanswered: the board may be homing
        self._homing_failed = False  # an ALARM came while a `$H` was unanswered
        self._storing: InFlight | None = None  # a line writing EEPROM or flash, unanswered
        self._stored_at: float | None = None  # when the last such line was answered
        self._stopping: float | None = None  # a feedhold waiting for rest, until then
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
        self._first_report = False  # the handshake waits for its first report
        self._banner_deadline: float | None = None
        self._handshake_deadline: float | None = None
        self._lines_in = 0

    # -- the dialect's parts: admission, flow, encoding (its words: words.py) ----------

    def _admit(self, cls: CommandClass, state: MachineState | None) -> int | None:
        return admit(cls, state, ADMISSION)

    def flushing(self) -> bool:
        return self._stopping is not None or self._resetting or self._held is not None

    def no_data_in_flight(self) -> bool:
        return not self._inflight

    def unanswered(self) -> int:
        return len(self._inflight)

    def quiet(self) -> bool:
        """As every session's, but a query in flight (`$$`, `$#`, `$G`: views that move
        nothing) leaves the machine quiet: a resume's `job.start` reads the board first,
        and a status report read meanwhile must not make the machine busy, and the job
        refused, until the next report."""
        if self._inflight and not all(
            codec.classify(entry.line.decode("ascii", "replace")) is CommandClass.QUERY
            for entry in self._inflight
        ):
            return False
        return not self._outbox and not self._job_running() and not self.flushing()

    def status_traffic(self, line: bytes, written: bool) -> bool:
        """`?` (grbl.h CMD_STATUS_REPORT) and the `<...>` report that answers it
        (report.c report_realtime_status)."""
        if written:
            return line.strip() == codec.STATUS
        return line[:1] == b"<" and line.rstrip()[-1:] == b">"

    def encode_job_line(self, text: str, number: int | None = None) -> bytes:
        if number is not None:
            if (
                text[:1] not in NOT_PREFIXED
                and 0 <= number <= MAX_LINE_NUMBER
                and text[-1:] != " "
                and "(" not in text
                and ";" not in text
            ):
                # `number_line`'s answer for almost every job line, and `codec.encode`'s
                # first branch on it: no comment to strip, no blank to strip at either end
                # (it starts with N; any other trailing blank fails the printable test).
                line = f"N{number} {text}"
                if len(line) < self.rx_size - 1 and codec.printable(line):
                    return (line + "\n").encode("ascii")
            text = number_line(text, number)
        return codec.encode(text, max_bytes=self.rx_size - 1)

    def override(
        self, feed: int | None = None, rapid: int | None = None, spindle: int | None = None
    ) -> None:
        """The override bytes (grbl.h CMD_OVERRIDE_*), by rounds, each followed by `?`s,
        until a report shows the values asked; then `override_answers` counts up.

        grbl's overrides are relative steps; an absolute percentage is a reset to
        100 then steps of 10 and of 1, all realtime bytes, taken in any state.
        Rapid has three settings: 100, 50 and 25; feed and spindle are refused
        outside 10..200, the firmware's own bounds.

        Neither firmware takes many at once. Classic grbl keeps one flag bit per
        kind (serial.c:167-181), applied once a main-loop pass (protocol.c:405-452):
        a reset and five "+10" that arrive within one pass make 110, not 150.
        grblHAL queues them in 16-slot rings (override.c:35-43), feed and rapid in
        one (protocol.c:941-950), and drops a byte that finds its ring full: the
        19 bytes of 100 to 199 lose their last. So a round writes what one pass
        takes (classic: one byte of a kind; grblHAL: OVERRIDE_RING a ring), the
        first from a reset, the next ones from what a report said, up to
        OVERRIDE_ROUNDS (`_Rounds`, `_override_round`).

        A `?` read in the same pass as the bytes is answered before they act
        (gnea/grbl protocol.c:250-253 before :405; grblHAL protocol.c:604-605
        before :629): the next round, or the answer, comes from a report asked
        after the one that answered that `?` (`_override_seen`). A round that
        brings no value nearer ends it: the answer is then what the board said,
        with a warning, never the values asked.
        """
        self._require_open()
        wanted: dict[str, int] = {}
        if feed is not None:
            codec.override_steps(feed, "feed")  # refuses a value outside 10..200
            wanted["feed"] = feed
        if rapid is not None:
            codec.rapid_override(rapid)
            wanted["rapid"] = rapid
        if spindle is not None:
            codec.override_steps(spindle, "spindle")
            wanted["spindle"] = spindle
        self._override = _Rounds(wanted)
        self._override_round(None)

    def _override_round(self, now: dict[str, float] | None) -> None:
        """One round's bytes (see `override`), then a `?`: from a reset when `now`, the
        values the board last reported, is None (the first round), else steps from them.

        The bytes are realtime: they go now, whatever line waits. The report that
        answers the round's `?` may predate them, as may one that answers an older
        `?` still unanswered: `hops` reports are read, a `?` asked after each,
        before one surely postdates them.
        """
        rounds = self._override
        assert rounds is not None
        wanted = rounds.wanted
        motion: list[bytes] = []  # feed and rapid: one ring on grblHAL
        accessory: list[bytes] = []
        if "rapid" in wanted and (now is None or now.get("rapid") != wanted["rapid"]):
            motion.append(codec.rapid_override(wanted["rapid"]))
        for what, ring in (("feed", motion), ("spindle", accessory)):
            if what not in wanted:
                continue
            value = None if now is None else now.get(what)
            start = None if value is None else int(value)
            if start is None or start != wanted[what]:
                ring += codec.override_steps(wanted[what], what, start)
        if self.flavour == "GrblHAL":
            motion, accessory = motion[:OVERRIDE_RING], accessory[:OVERRIDE_RING]
        else:  # one byte of a kind; in the order protocol.c applies them (reset, 10s, 1s)
            motion, accessory = list(dict.fromkeys(motion)), list(dict.fromkeys(accessory))
        self._out += [(Lane.REALTIME, b) for b in motion + accessory]
        rounds.rounds += 1
        rounds.hops = 2 if self._asked_at is None else 3
        rounds.asks = OVERRIDE_ASKS
        self._ask_report()

    def _override_seen(self, report: codec.StatusReport, fresh: bool) -> None:
        """A report while an override's rounds run (`override`); `fresh`: it has `Ov:`."""
        rounds = self._override
        assert rounds is not None
        rounds.hops -= 1
        if rounds.hops > 0:
            self._ask_report()  # this report may predate the round's bytes: ask again
            return
        now = self.model.overrides
        if not fresh and rounds.asks and (now is None or "WCO" in report.fields):
            # No `Ov:`: with no change since the last one the board sends none for up
            # to 20 reports (report.c:615-619), but classic grbl also defers one a
            # report when it prints WCO (report.c:608): ask again.
            rounds.asks -= 1
            rounds.hops = 1
            self._ask_report()
            return
        gap = None if now is None else rounds.gap_to(now)
        why = None
        if gap == 0:
            pass
        elif gap is None:
            why = "the board reports no overrides"
        elif rounds.final:
            why = "the controller was reset meanwhile"
        elif rounds.gap is not None and gap >= rounds.gap:
            why = "the last round brought them no nearer"
        elif rounds.rounds >= OVERRIDE_ROUNDS:
            why = f"not there after {OVERRIDE_ROUNDS} rounds"
        else:
            rounds.gap = gap
            self._override_round(now)
            return
        if why is not None:
            self._log.warning("overrides not as asked", asked=rounds.wanted, reported=now, why=why)
        self._override = None
        self.override_answers += 1

    def safety_door(self) -> None:
        """0x84 (protocol.c CMD_SAFETY_DOOR): the board enters Door as if its switch opened."""
        self._require_open()
        self._out.append((Lane.REALTIME, codec.SAFETY_DOOR))

    def next_deadline(self) -> float | None:
        if self._closing_reason is not None:
            return None
        deadline = None  # asked after every step: no list built
        for d in (self._banner_deadline, self._handshake_deadline, self._stopping):
            if d is not None and (deadline is None or d < deadline):
                deadline = d
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

    # -- the connection ------------------------------------------------------------

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
        self._homing_lines = 0
        self._homing_failed = False
        self._storing = None

    def _settle_lost(self, entry: InFlight, error: MachineError) -> None:
        if entry.file_line is not None:
            entry.source.discarded += 1
        else:
            self._settle(entry.source, error)

    # -- reading -----------------------------------------------------------------------

    def receive(self, line: bytes) -> None:
        self._heard_at = self.clock()  # any line, `ok`s too: the board lives
        if self._silent_asks:
            self._silent_asks.clear()
        if line == b"ok" and self._job_ok():
            return
        msg = codec.parse(line)
        if isinstance(msg, codec.Ok | codec.Error):
            self._answered(msg)
        elif isinstance(msg, codec.StatusReport):
            self._on_report(msg)
        elif isinstance(msg, codec.Alarm):
            self._on_alarm(msg.code)
        elif isinstance(msg, codec.Welcome):
            self._on_welcome(msg)
        elif isinstance(msg, codec.Feedback):
            self._on_feedback(msg)
        elif isinstance(msg, codec.Setting):
            self.settings[msg.key] = msg.value
            self._said.append(f"${msg.key}={msg.value}")
            if msg.key == "32":
                self.model.laser_mode = msg.value.strip() == "1"
        elif isinstance(msg, codec.Garbage):
            self._job_log().warning("unparseable controller output", reason=msg.reason, raw=line)
            kind = "serial" if msg.reason == "not valid ASCII" else "lexical"
            self._detected(kind, self._lines_in, f"{msg.reason}: {line[:60]!r}")
            return
        elif msg.text:
            self._said.append(msg.text)
        self._lines_in += 1

    def receive_plain(self, lines: list[bytes], start: int) -> int:
        """`receive`'s `_job_ok` for a run of `ok`s, each the answer to the job's oldest
        line, booked together. Not at the job's end (its input ended, or a refused
        line's turn came: each answer then checks whether the job is complete), nor
        while a line writes EEPROM or homes; a `$` line's `ok` is read in full."""
        stream = self._steady_stream()
        if stream is None or self._storing is not None or self._homing_lines:
            return start
        inflight = self._inflight
        answered: list[int] = []
        freed = 0
        index = start
        for line in lines[start:] if start else lines:
            if line != b"ok" or not inflight:
                break
            entry = inflight[0]
            encoded = entry.line
            if entry.source is not stream or encoded[:1] == b"$":
                break
            inflight.popleft()
            freed += len(encoded)
            answered.append(entry.file_line)  # type: ignore[arg-type]  # a job's line has one
            index += 1
        if answered:
            self._heard_at = self.clock()  # `receive`'s first steps, once for the run
            if self._silent_asks:
                self._silent_asks.clear()
            self._rx_used -= freed
            if self._said:
                self._said = []
            self._lines_in += len(answered)
            stream.acknowledged_run(answered)
        return index

    def _job_ok(self) -> bool:
        """An `ok` for the oldest line, a job's plain line: what `_answered` would do
        with it, without its message and its Response; False, and nothing done, for
        any other line (no line waiting, a `$` line, one that homes or stores)."""
        inflight = self._inflight
        if not inflight:
            return False
        entry = inflight[0]
        line = entry.line
        if (
            entry.file_line is None
            or line[:1] == b"$"
            or entry is self._storing
            or (self._homing_lines and codec.homes(line))
        ):
            return False
        inflight.popleft()
        self._rx_used -= len(line)
        if self._said:
            self._said = []  # what the board printed before it: a job line's ok carries none
        self._lines_in += 1
        if entry.source.acknowledged(entry.file_line):
            self._check_stream_complete()
        return True

    def _answered(self, msg: codec.Ok | codec.Error) -> None:
        if not self._inflight:
            self._job_log().warning("answer with no line waiting", answer=msg)
            self._detected("lexical", None, f"an answer with no line waiting: {msg!r}")
            return
        entry = self._inflight.popleft()
        self._rx_used -= len(entry.line)
        if entry is self._storing:
            self._storing = None
            self._stored_at = self._heard_at
        homing = self._homing_lines > 0 and codec.homes(entry.line)
        if homing:
            self._homing_lines -= 1
        status = 0 if isinstance(msg, codec.Ok) else msg.code
        body: dict[str, Any] = {"lines": self._said} if self._said else {}
        self._said = []
        response = Response(body, status, 0, b"ok" if status == 0 else b"error:%d" % status)
        if homing and not self._homing_lines:
            failed, self._homing_failed = self._homing_failed, False
            if status == 0 and not failed:
                # A client's `$H` or a job's. Classic grbl answers a failed cycle `ok`
                # too, after its ALARM (system.c: `$H` breaks out with STATUS_OK).
                self.model.homed = True
        if status == 0 and entry.line.upper() == b"$N\n":
            self._startup_read()  # ours at connect and after a reset, or a client's
        source = entry.source
        if entry.file_line is not None:
            self._on_job_answer(source, entry, response)
        elif isinstance(source, _Own):
            self._own_answered(source, response)
        else:
            self._settle(source, response)

    def _on_job_answer(self, stream: Stream, entry: InFlight, response: Response) -> None:
        if response.ok:
            stream.acknowledged(entry.file_line)
            self._check_stream_complete()
            return
        stream.rejected += 1
        if stream.done:
            return
        status = response.status
        if status in LOCKOUT_ERRORS and self.locked():
            code = self._admit(CommandClass.ACTION, self.model.state) or _REFUSED_BY_ALARM
            self._end_stream(stream, StreamEnd.FAILED, code, error_text(status))
            return
        self._end_stream(
            stream,
            StreamEnd.FAILED,
            ControllerError.code,
            f"line {entry.file_line}: controller answered error:{status}: {error_text(status)}",
        )
        if self.model.board_state != "Check":
            # The lines behind it are in the board's buffer and would run: stop it.
            self._begin_stop()

    def _on_report(self, report: codec.StatusReport) -> None:
        ov_reports = self.model.override_reports
        fields = self._reports.fields(report, self.model)
        before = self.model.state
        self.model.board_state = report.state + ("" if report.sub is None else f":{report.sub}")
        changed = self.model.apply_status(fields)
        self._asked_at = None
        self._await_report = False
        if changed is not None:
            self._on_state(changed, before)
        if self._hold_settling:
            self._hold_settled(report)
            if self._hold_settling:  # still stopping: look again soon, not a poll away
                self._poll_soon()
        elif self._resume_asks:
            self._resume_seen(report)
        if self._override is not None:
            self._override_seen(report, self.model.override_reports != ov_reports)
        self._track_executed(fields)
        self._events.append(Reported(fields, self.model.snapshot()))
        waiters, self._report_waiters = self._report_waiters, []
        for token in waiters:
            self._settle(token, Response({"report": grbl_named(report)}, 0, 0, b"?"))
        if self._stopping is not None and self._at_rest_for_reset(report):
            self._stop_reset()
        if self._awaiting_rest:
            self._check_stream_complete(reported=True)
        if self._first_report:
            self._ready()

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

    def _poll_soon(self) -> None:
        """The next `?` within SETTLE_POLL, not a `status_interval` away."""
        self._next_poll = min(self._next_poll, self.clock() + SETTLE_POLL)

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

    def _track_executed(self, fields: dict[str, Any]) -> None:
        """Which file line runs: `Ln:`, else what the planner can still hold.

        `Ln:` is the N of the planner block being executed (report.c: the current
        block, or on grblHAL the parser's last N when the planner is empty: all of it
        ran). It is sent by grblHAL when `$10` asks for it and by classic grbl only when
        built with USE_LINE_NUMBERS (off by default). Without it, `Bf:` bounds it: grbl
        answers `ok` once a line is planned, so of the lines answered, only the last
        `blocks - free` can still be in the planner; the one before them ran.
        """
        stream = self.stream
        if stream is None or stream.done:
            return
        line = fields.get("line")
        if isinstance(line, int) and line > 0:
            stream.executing(line)
        if self._reports.planner_free is not None and stream.acked:
            used = max(self.blocks - self._reports.planner_free, 0)
            ran = stream.acked_line(used)
            if ran is not None and ran > 0:
                stream.executing(ran)

    def _at_rest(self) -> bool:
        """Idle with blocks still planned is the instant before a cycle starts (Bf says)."""
        planner_empty = (
            self._reports.planner_free is None or self._reports.planner_free >= self.blocks
        )
        return super()._at_rest() and planner_empty

    def _on_state(self, state: MachineState, before: MachineState | None) -> None:
        self._job_log().info("controller state", state=state.name)
        if state.is_lockout:
            self._drain_for_lockout(state, lambda _code: "the controller is locked out")
        self._recheck_waiting()

    def _on_alarm(self, code: int) -> None:
        if self._homing_lines:
            self._homing_failed = True
        text = alarm_text(code)
        state = ALARM_STATE.get(code, MachineState.ALARM)
        report = {"alarm": code, "msg": text}
        self.model.last_exception = report
        if code in POSITION_LOST:
            self.model.homed = False
        if code in CRITICAL:
            self._needs_reset = code
        self._job_log().warning("controller alarm", alarm=code, msg=text)
        self._events.append(Excepted(report))
        before, self.model.state = self.model.state, state
        self._on_state(state, before)
        # Nothing of ours is written until a report says where the board is.
        self._await_report = True
        self._query_status()

    def _on_welcome(self, welcome: codec.Welcome) -> None:
        self.flavour, self.version = welcome.flavour, welcome.version
        if self.phase is Phase.HANDSHAKE and not self._resync:
            self._ask_build()
            return
        # A reset: ours (a cancel, machine.reset) or the board's own. It forgot every line.
        ours = self._resetting
        self._resetting = False
        if self._override is not None:
            # The reset set every override to 100 (and grblHAL flushed its rings,
            # protocol.c:595): no more rounds; the next report's `Ov:` is the answer.
            self._override.final = True
            self._override.hops = 1
        self._needs_reset = None
        self._stopping = None
        self._held = None
        self._forget_holds()
        if self.stream is not None and not self.stream.done:
            self._end_stream(self.stream, StreamEnd.FAILED, 1005, "the controller was reset")
        what = "reset" if ours else "reset by itself"
        self._forget(ControllerError(int(Status.NOOP), f"discarded by the controller's {what}"))
        self.model.state = None  # a report will say (an e-stop's SHUTDOWN is over)
        self._reports = ReportReader()  # a reset clears G92: the offset is read anew
        self._job_log().info("controller reset", ours=ours)
        self.phase = Phase.HANDSHAKE
        self._resync = True
        self._handshake_deadline = self.clock() + self.handshake_timeout
        self._ask_own("$N", _Own.STARTUP)  # then `$G`: a `$RST=*` may have cleared them

    def _on_feedback(self, msg: codec.Feedback) -> None:
        text = f"[{msg.kind}:{msg.text}]"
        if msg.kind == "PRB":
            report = probe_report(msg.text)
            self._events.append(Probed(report, self.model.apply_probe(report)))
        elif msg.kind == "GC":
            apply_modes(self.model, msg.text)
        elif msg.kind == "OPT":
            parts = msg.text.split(",")
            if len(parts) >= 3 and parts[1].isdigit() and parts[2].isdigit():
                self.blocks, self.rx_size = int(parts[1]), int(parts[2])
        elif msg.kind == "FIRMWARE" and msg.text == "grblHAL":
            self.flavour = "GrblHAL"  # `$I` (report.c:1076): a native USB port prints no banner
        elif msg.kind == "MSG":
            self._job_log().info("controller message", msg=msg.text)
        self._said.append(text)

    # -- the handshake ---------------------------------------------------------------

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

    # -- writing -----------------------------------------------------------------------

    def _room(self, line: bytes) -> bool:
        return self._rx_used + len(line) <= self.rx_size - 1

    def _pump(self) -> None:
        if self.phase is not Phase.READY or self.halted or self.flushing():
            return
        if self._storing is not None:
            return  # bytes arriving while the board writes EEPROM are lost: wait for its answer
        state = self.model.state
        # Judged only when a client's line waits: most passes carry job lines alone.
        context = self._context() if self._outbox else Context.FREE
        while self._outbox:
            head = self._outbox[0]
            if not self._room(head.encoded):
                return  # in order: a client's lines never overtake each other
            if self._await_report and head.context is not Context.ANY:
                return
            if head.cls is CommandClass.CLEAR and self._inflight:
                return  # a stale line must not run after the unlock
            queued = self._outbox.popleft()
            if self._admissible(queued, state, context):
                self._book(queued.encoded, queued.token)
                if self._storing is not None:
                    return  # send-response: the next line waits for this one's answer
        stream = self.stream
        if (
            stream is None
            or stream.done
            or stream.paused
            or self._await_report
            or (state is not None and (state.is_lockout or state in _NO_JOB_LINES))
        ):
            return
        # `_room` and `_special`'s first test written out: this loop runs for every job line.
        room = self.rx_size - 1
        inflight = self._inflight
        out = self._out
        data = Lane.DATA
        if self.fast_path:
            # The steady state: the plain lines ahead that the receive buffer has room
            # for, taken and booked together; the loop below goes on from the first line
            # it left (a `$` line, one that may store, one that does not fit).
            taken = stream.take_run(room - self._rx_used, by_bytes=True, special=_MAY_STORE)
            if taken:
                inflight.extend(taken)
                pairs = [(data, entry.line) for entry in taken]
                out.extend(pairs)
                self._rx_used += sum([len(line) for _, line in pairs])
        while True:
            entry = stream.peek()
            if entry is None:
                self._check_stream_complete()
                return
            line = entry.line
            if self._rx_used + len(line) > room:
                return
            stream.take()
            inflight.append(entry)
            self._rx_used += len(line)
            out.append((data, line))
            if (line[:1] == b"$" or _MAY_STORE(line)) and self._special(entry):
                return

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

    def _book(self, encoded: bytes, source: Any) -> None:
        entry = InFlight(encoded, source, None, isinstance(source, _Own))
        self._inflight.append(entry)
        self._rx_used += len(encoded)
        self._out.append((Lane.DATA, encoded))
        self._special(entry)

    def _ask_own(self, text: str, purpose: _Own) -> None:
        """A line of the session's own: it goes now, budget or not (they are few and short)."""
        if self.phase is not Phase.CLOSED:
            self._book(codec.encode(text), purpose)

    def _ask_report(self) -> None:
        now = self.clock()
        self._asked_at = now
        self._next_poll = now + self.status_interval
        if len(self._silent_asks) < SILENT_QUERIES:
            self._silent_asks.append(now)
        self._out.append((Lane.REALTIME, codec.STATUS))

    def _query_status(self) -> None:
        if self.phase is not Phase.CLOSED:
            self._ask_report()

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
        the reset, unless the config allows it: the board stays in its feedhold,
        nothing more is written (`flushing`), and the operator decides, with
        machine.reset, which runs the block.
        """
        moving = [b for b in self.model.startup_blocks or () if b["acts"]]
        if moving and not self.startup_motion:
            self._stopping = None
            blocks = "; ".join(f"$N{b['n']}={b['line']} {b['acts']}" for b in moving)
            self._held = (
                f"{self.id} is held instead of reset: the startup block {blocks} at every "
                "reset; machine.reset runs it, or allow it with startup_motion = true"
            )
            self._job_log().warning("stop held: a startup block would act", blocks=blocks)
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

    # -- requests --------------------------------------------------------------------------

    def send(self, line: str, token: Any, *, operation: bool = False) -> None:
        self._require_ready()
        if self.halted:
            raise self._write_refused()
        text = line.strip()
        if text == "?":
            self._report_waiters.append(token)
            self._ask_report()
            return
        if self._held is not None:
            raise Busy(self._held)  # nothing is written until the operator resets
        cls = codec.classify(text)
        verdict = self._admit(cls, self.model.state)
        if verdict is not None:
            raise Rejected(verdict, self._locked_message())
        self._refuse_until_reset()
        encoded = codec.encode(text, max_bytes=self.rx_size - 1)
        if cls in (CommandClass.QUERY, CommandClass.CLEAR):
            self._outbox.append(Queued(encoded, cls, token, Context.ANY))
            return
        context = self._context()
        if operation and self._operation and context is Context.JOB:
            self._outbox.append(Queued(encoded, cls, token, Context.OPERATION))
        elif context is Context.JOB:
            raise Busy(f"{self.id} is running {'a job' if self._job_running() else 'an operation'}")
        elif context is Context.HOLD or self.model.state is MachineState.INTERLOCK:
            raise Busy(f"{self.id} is in a hold: grbl runs no line inside one; resume first")
        else:
            self._outbox.append(Queued(encoded, cls, token, context))

    def _refuse_until_reset(self) -> None:
        """After a critical alarm the board reads no line until it is reset (then `$X`)."""
        if self._needs_reset is not None:
            raise Rejected(
                _REFUSED_BY_ALARM,
                f"{self._locked_message()}: the controller reads nothing until a reset "
                "(machine.reset), then clear",
            )

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


_NO_JOB_LINES = frozenset({MachineState.HOLD, MachineState.INTERLOCK})
_MAY_STORE = codec.MAY_STORE.search
