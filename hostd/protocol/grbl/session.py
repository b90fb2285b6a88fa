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

`GrblSession` is one class written in layers, a file each, as g2core's is; a
layer calls only itself, the layers below it and SessionBase, and none
overrides another (docs/architecture.md):

  books.py       GrblBooks       every field (__init__), the books, ADMISSION
  flow.py        GrblFlow        send, _pump, the job's `ok`s, encode_job_line
  holds.py       GrblHolds       our `!` settling, our `~` and its `?`s
  overrides.py   GrblOverrides   override by rounds
  stops.py       GrblStops       stops, resets, realtime, lockout exits
  connection.py  GrblConnection  open, close, the handshake's steps
  liveness.py    GrblLiveness    tick, next_deadline, the link's silence
  session.py     GrblSession     receive and what the board prints
"""

from __future__ import annotations

from typing import Any

from hostd.protocol.classes import CommandClass
from hostd.protocol.errors import ControllerError
from hostd.protocol.grbl import codec
from hostd.protocol.grbl.books import _REFUSED_BY_ALARM, _Own
from hostd.protocol.grbl.codes import (
    ALARM_STATE,
    CRITICAL,
    IDLE_ERROR,
    LOCKOUT_ERRORS,
    POSITION_LOST,
    alarm_text,
    error_text,
)
from hostd.protocol.grbl.liveness import GrblLiveness
from hostd.protocol.grbl.report import ReportReader, apply_modes, grbl_named, probe_report
from hostd.protocol.linemode import InFlight
from hostd.protocol.messages import Response
from hostd.protocol.states import MachineState
from hostd.protocol.stream import Stream
from hostd.protocol.vocabulary import Excepted, Phase, Probed, Reported, StreamEnd

# What `$I` prints before its `ok` (`_stale`): `[VER:...]` (report.c report_build_info).
_BUILD_PRINTOUT = "[VER:"

# s between `?`s once a job's every line is answered and its end waits for a report of
# the board at rest: grbl pushes no report when its planner runs dry, so at the poll's
# `status_interval` (0.25 s) the end was seen up to that late; 20 `?`s a second while the
# last moves run cost a report each.
END_POLL = 0.05


class GrblSession(GrblLiveness):
    """grbl 1.1's and grblHAL's session (see the module's docstring): its reading."""

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
            self._setting_seen(msg.key, msg.value)
            self._said.append(f"${msg.key}={msg.value}")
        elif isinstance(msg, codec.Garbage):
            self._job_log().warning("unparseable controller output", reason=msg.reason, raw=line)
            kind = "serial" if msg.reason == "not valid ASCII" else "lexical"
            self._detected(kind, self._lines_in, f"{msg.reason}: {line[:60]!r}")
            return
        elif msg.text:
            self._said.append(msg.text)
        self._lines_in += 1

    def _answered(self, msg: codec.Ok | codec.Error) -> None:
        if self.phase is Phase.HANDSHAKE and self._stale(msg):
            return
        if not self._inflight:
            self._job_log().warning("answer with no line waiting", answer=msg)
            self._detected("lexical", None, f"an answer with no line waiting: {msg!r}")
            return
        entry = self._inflight.popleft()
        self._rx_used -= len(entry.line)
        self._alarm_unanswered = None
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
        if status == 0 and entry.line[:1] == b"$":
            if entry.line.upper() == b"$N\n":
                self._startup_read()  # ours at connect and after a reset, or a client's
            else:
                self._setting_written(entry.line)
        source = entry.source
        if entry.file_line is not None:
            self._on_job_answer(source, entry, response)
        elif isinstance(source, _Own):
            self._own_answered(source, response)
        else:
            self._settle(source, response)
            if status == 0 and entry.line[:1] != b"$":
                self._modes_changed()

    def _stale(self, msg: codec.Ok | codec.Error) -> bool:
        """An answer read while connecting that answers a line of before this link: the
        board went on answering the lines it held (a job's, after a lost link or a
        dead daemon), and the port kept what it printed. All of them come before the
        answer to the handshake's first line, `$I`, which prints `[VER:...]` before
        its `ok`: an answer without it is not `$I`'s (taken as `$I`'s, it would make
        the board's build and settings unknown), nor is one with no line of ours out.
        An `error:` likewise, but error:8, the refusal of a busy board
        (`_own_answered`). The lines after `$I` are answered in order behind it, and
        are taken as they come (a build with no startup lines prints none for `$N`)."""
        if isinstance(msg, codec.Error) and msg.code == IDLE_ERROR:
            return False
        if self._inflight:
            if self._inflight[0].source is not _Own.BUILD:
                return False
            if any(said.startswith(_BUILD_PRINTOUT) for said in self._said):
                return False
        self._said = []
        self._stale_answers += 1
        if self._stale_answers == 1:
            self._job_log().info("answers from before this link are dropped")
        return True

    def _modes_changed(self) -> None:
        """A client's G-code line ran, or a job completed: `$G`, since grbl reports its
        modes (units, distance, WCS, tool) nowhere else. A jog is in the units mode, and
        its bound is checked in it (guard.py): after a client's `G20` the session must
        know. A reset asks anew by itself (the handshake)."""
        if self.phase is Phase.READY:
            self._ask_own("$G", _Own.MODES)

    def _end_stream(
        self, stream: Stream, end: StreamEnd, code: int | None = None, message: str | None = None
    ) -> None:
        done = stream.done
        super()._end_stream(stream, end, code, message)
        if not done and end is StreamEnd.COMPLETED:
            self._modes_changed()  # its lines may have left G20, G55, ..

    def _setting_seen(self, key: str, value: str) -> None:
        """A setting as the board printed it (`$$`, `$n`)."""
        self.settings[key] = value
        if key == "32":
            self.model.laser_mode = value.strip() == "1"

    def _setting_written(self, line: bytes) -> None:
        """A `$n=v` the board took (answered ok): what it now holds, without a `$$`. Classic
        grbl keeps its flag settings as bits (gnea/grbl settings.c:243-296: any value but
        0 sets the flag, `$$` then says 1); grblHAL keeps the number."""
        found = codec.setting_write(line)
        if found is None:
            return
        key, value = found
        if self.flavour != "GrblHAL" and key in codec.CLASSIC_FLAGS:
            number = codec.numbers(value)
            value = "1" if number and number[0] != 0 else "0"
        self._setting_seen(key, value)

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
        if self._asks:
            self._asks.pop()
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
        if self._stopping is not None:
            if self._stop_skips:  # it may predate the stop's `!` (`_begin_stop`): ask again
                self._stop_skips -= 1
                self._ask_report()
            elif self._at_rest_for_reset(report):
                self._stop_reset()
        if self._awaiting_rest:
            self._check_stream_complete(reported=True)
            if self._awaiting_rest and report.state == "Run":  # the job's last moves run
                self._poll_soon(END_POLL)  # (not while held: a resume asks for itself)
        if self._first_report:
            self._ready()
        elif self.phase is Phase.HANDSHAKE and not self._resync:
            # Not in the re-sync after a reset: the board was just emptied, and what moves
            # then is a startup block, not moves of before this link.
            self._connecting_report(report)

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

    def line_running(self) -> int | None:
        """`Ln:` (`_track_executed`): the block being executed, or on grblHAL with the
        planner empty the parser's last, which ran. None without it (classic grbl built
        without USE_LINE_NUMBERS): `Bf:` bounds a job's line only from the job's own
        answers."""
        line = self.model.line
        return line if line is not None and line > 0 else None

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
        self._alarm_unanswered = f"ALARM:{code} ({text})"
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
            if self._resetting:  # ours, before the handshake was through: it forgot `$I`
                self._restart_handshake()
            else:
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
        # Status 0: grbl gives no code for this (its error:3 is an unknown `$` command).
        if ours:
            what, why = "the controller was reset", "discarded by the controller's reset"
        else:  # after an alarm when it came with no answer since: a failed `$H`, a limit
            alarm = self._alarm_unanswered
            what = why = "the controller reset itself" + (f" after {alarm}" if alarm else "")
        self._alarm_unanswered = None
        if self.stream is not None and not self.stream.done:
            self._end_stream(self.stream, StreamEnd.FAILED, 1005, what)
        self._forget(ControllerError(0, f"not answered: {why}"))
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
                # The build's letters: `N` is USE_LINE_NUMBERS on classic grbl (gnea/grbl
                # report.c:379-381, off by default), always there on grblHAL (core
                # report.c:897). Without it no `Ln:` ever comes: job lines go unnumbered.
                self.line_numbers = "N" in parts[0]
        elif msg.kind == "FIRMWARE" and msg.text == "grblHAL":
            self.flavour = "GrblHAL"  # `$I` (report.c:1076): a native USB port prints no banner
        elif msg.kind == "MSG":
            self._job_log().info("controller message", msg=msg.text)
        self._said.append(text)
