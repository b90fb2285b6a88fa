"""G2Session's connection: open, the handshake, the heartbeat, close.

A layer of `G2Session` (g2core.py). The handshake (g2core.md section 10): the
banner, or after `BANNER_WAIT` on a link that prints none a version request;
the firmware build checked; the protocol settings; `{home:n}`; a full status
report. What it accepts and sends is in g2handshake.py; its steps are here.
Then the heartbeat: a board silent for `heartbeat` seconds is asked for a
report, and one that does not answer within as long again is gone.
"""

from __future__ import annotations

from collections import deque

from hostd.protocol.commands import encode_get, encode_set
from hostd.protocol.errors import NotConnected
from hostd.protocol.g2books import _Own
from hostd.protocol.g2builds import Build
from hostd.protocol.g2handshake import (
    BANNER_WAIT,
    SPINDLE_KEYS,
    check_firmware,
    protocol_settings,
)
from hostd.protocol.g2lockouts import _LOCKOUT_REJECTIONS, G2Lockouts
from hostd.protocol.g2words import setting_number
from hostd.protocol.linemode import InFlight
from hostd.protocol.messages import Banner, Response
from hostd.protocol.status import message
from hostd.protocol.vocabulary import Phase, Ready


class G2Connection(G2Lockouts):
    """A connection's life, and the answers to the session's own lines (see `G2Session`)."""

    # -- outputs ---------------------------------------------------------------

    def next_deadline(self) -> float | None:
        if self._closing_reason is not None:
            return None
        deadline = None  # asked after every step: no list built
        for d in (
            self._banner_deadline,
            self._handshake_deadline,
            self._flush_deadline,
            self._heartbeat_deadline,
        ):
            if d is not None and (deadline is None or d < deadline):
                deadline = d
        if self.phase is Phase.READY and self.heartbeat and self._heartbeat_deadline is None:
            beat = self._last_rx + self.heartbeat
            if deadline is None or beat < deadline:
                deadline = beat
        return deadline

    # -- the connection --------------------------------------------------------

    def open(self, *, rebooting: bool = False) -> None:
        """The link is open: begin the handshake. After 0x18 only the banner will do."""
        now = self.clock()
        self.phase = Phase.HANDSHAKE
        self._closing_reason = None
        self._rebooting = rebooting
        self._identity = None
        self._last_rx = now
        self._handshake_deadline = now + self.handshake_timeout
        # A board on a UART link prints its banner only at boot, not when a host
        # opens the port: if none comes soon, ask for the version instead.
        wait = min(BANNER_WAIT, self.handshake_timeout / 2)
        self._banner_deadline = None if rebooting else now + wait

    def close(self, reason: str, *, restarted: bool = False) -> None:
        """The link is gone: settle every line and request it carried."""
        self.phase = Phase.CLOSED
        self._flush = None
        self._kills_unseen = self._control_fences = 0
        self._kill_alarm = self._alarm_kill_due = False
        self._held = None
        self._banner_deadline = self._handshake_deadline = None
        self._flush_deadline = self._heartbeat_deadline = None
        lost = NotConnected(f"link lost: {reason}")
        for entry in self.sender.clear():
            self._settle_unanswered(entry, lost)
        for waiting in (self._outbox, self._lane):
            while waiting:
                self._settle(waiting.popleft().token, lost)
        self._end_stream_on_close(reason, restarted)
        self._await_report = self._awaiting_rest = False
        self._settings_pending = False
        self._rest_at, self._moved = None, False
        self._auto_sr.clear()  # a board that starts again reports from nothing
        self._to_set.clear()
        self._spindle_asks.clear()
        self.spindle_keys = ()
        self._lines_in = 0
        self._out.clear()
        self.model.reset()

    # -- timers ----------------------------------------------------------------

    def tick(self) -> None:
        """A deadline passed (or the engine woke early: nothing is due then)."""
        now = self.clock()
        if self._closing_reason is not None:
            return
        if self._handshake_deadline is not None and now >= self._handshake_deadline:
            self._handshake_timed_out()
            return
        if self._banner_deadline is not None and now >= self._banner_deadline:
            self._banner_deadline = None
            self._ask_own(encode_get("fv", "fb"), _Own.VERSION)
        if self._flush_deadline is not None and now >= self._flush_deadline:
            # A `%` outside a hold flushes nothing: its lines will be answered as usual.
            # A kill's fence still unread (the board does not read its data port): data
            # lines may go again, behind it; its answer still settles the lines before it.
            self._log.warning("flush not confirmed by the controller")
            self._flush = self._flush_deadline = None
            self._kills_unseen = 0
        if self.phase is not Phase.READY or not self.heartbeat:
            return
        if self._heartbeat_deadline is not None:
            if now >= self._heartbeat_deadline:
                silent = 2 * self.heartbeat
                self._closing(f"controller silent for {silent:g} s (no answer to a status request)")
        elif now >= self._last_rx + self.heartbeat:
            # A silent board is asked for a report; one that stays silent is gone.
            self._heartbeat_deadline = now + self.heartbeat
            self._ask_own(encode_get("sr"), _Own.HEARTBEAT)

    # -- the handshake ---------------------------------------------------------

    def _identified(self, fb: float | None) -> None:
        try:
            check_firmware(fb)
        except NotConnected as exc:
            self._closing(exc.message)
            return
        self._identity = fb
        assert fb is not None  # check_firmware refuses a board that did not say
        self.build = Build(fb)
        self.spindle_keys = ()
        self._spindle_asks = deque(SPINDLE_KEYS)
        self._ask_spindle()

    def _ask_spindle(self) -> None:
        """Which spindle keys the board has (g2handshake.py SPINDLE_KEYS): one GET of each
        set's first key, until one is answered; then the settings, with that set listed."""
        if self._spindle_asks:
            self._ask_own(encode_get(self._spindle_asks[0][0]), _Own.SPINDLE)
            return
        keys = self.spindle_keys
        self._to_set = deque(protocol_settings(self.status_interval, self.signal_keys, keys))
        self._next_setting()

    def _spindle_answered(self, response: Response) -> None:
        keys = self._spindle_asks.popleft()
        if response.ok:
            self.spindle_keys = keys
            self._spindle_asks.clear()
            self.model.apply_status(response.body)
        self._ask_spindle()

    def _next_setting(self) -> None:
        if self._to_set:
            self._ask_own(encode_set(self._to_set[0]), _Own.SETTING)
        else:
            self._read_overrides()  # answered before the report that makes the session ready
            self._ask_own(encode_get("home"), _Own.HOMED)
            self._ask_own(encode_get("sr"), _Own.FIRST_REPORT)

    def _own_answered(self, own: _Own, entry: InFlight, response: Response) -> None:
        if own is _Own.VERSION and self.phase is Phase.HANDSHAKE:
            self._identified(setting_number(response.body.get("fb")))
        elif own is _Own.SPINDLE and self._spindle_asks:
            self._spindle_answered(response)
        elif own is _Own.SETTING and self._to_set:
            setting = self._to_set.popleft()
            if response.status in _LOCKOUT_REJECTIONS:
                # A board in ALARM refuses every SET: sent again once it is cleared.
                self._settings_pending = True
            elif not response.ok:
                status = response.status
                self._closing(f"controller refused {setting}: {status} ({message(status)})")
                return
            self._next_setting()
        elif own is _Own.HOMED and response.ok:
            self.model.apply_status({"home": response.body.get("home")})
        elif own is _Own.FIRST_REPORT and self.phase is Phase.HANDSHAKE:
            self.phase = Phase.READY
            self._handshake_deadline = None
            self._events.append(Ready())
        elif own is _Own.OVERRIDES:
            self._overrides_answered(response)
        elif own is _Own.HEARTBEAT:
            self._heartbeat_deadline = None
        elif own is _Own.FENCE:
            self._control_fences = max(0, self._control_fences - 1)
            self._kill_fenced()
        elif own is _Own.CLEAR and not response.ok:
            self._log.error("controller refused the clear after a kill", status=response.status)
        elif own is _Own.REAPPLY and not response.ok:
            self._log.error("controller refused a setting", setting=entry.line)

    def _handshake_timed_out(self) -> None:
        step = (
            "answer to its settings"
            if self._identity is not None
            else "SYSTEM READY banner"
            if self._banner_deadline is None and self._rebooting
            else "SYSTEM READY banner, nor an answer to a version request,"
        )
        timeout = self.handshake_timeout
        self._closing(f"no {step} from the controller within {timeout:g} s")

    def _on_banner(self, banner: Banner) -> None:
        if self.phase is Phase.HANDSHAKE:
            if (self._identity is None and self._banner_deadline is not None) or self._rebooting:
                self._banner_deadline = None
                self._rebooting = False
                self._identified(banner.fb)
            return  # a banner while we already asked for the version: that answer decides
        # SYSTEM READY mid-session: the board restarted under us.
        self._closing("controller restarted (unexpected SYSTEM READY)")
