"""The simulated grbl 1.1h / grblHAL: its state, receive buffer, main loop and alarms.

The firmware's main loop without the hardware, like the g2core board
(hostd/sim/board.py): the controller feeds received bytes to `receive()`
(the serial interrupt: realtime characters are acted on at once, the rest
go into the receive ring or are lost when it is full) and calls `tick()`
until it reports no progress, then sleeps until `next_deadline()` or new
input. Output leaves as text lines through `emit`; the controller adds the
firmware's CRLF (stream.h ASCII_EOL "\\r\\n", gnea/grbl report.c "\\r\\n").
No I/O and no asyncio here; the clock is injected.

`GrblBoard` holds all of the board's state and is the one object the
controller and the tests use. The rest of the firmware is in modules of
functions that take the board, cut where the firmware's own files are:
system.py (`$` commands, system.c), reports.py (`?`, `$G`, `$#`, `$I`,
report.c), realtime.py (the realtime characters), lines.py (a line read
from the receive ring and run; protocol.c), motion_control.py (the
planner's blocks, what a line waits for, homing's end, probing;
motion_control.c) and settings.py (the `$n` defaults). They read and
write the board's underscored attributes too: those are private to this
package, not to this module. Each names the sources of its own rules; this
module's are below.

Sources, read from grblHAL/core (f80fc34) and gnea/grbl (bfb67f0, 1.1h);
"HAL" marks a grblHAL-only rule, "classic" a grbl 1.1-only one (here and in
the modules above):

- receive ring: gnea/grbl serial.c (RX_BUFFER_SIZE 128, a byte arriving at a
  full ring is dropped); grblHAL drivers' serial.c (`next_head == tail`:
  `rxbuf.overflow = On`, the byte is dropped). Realtime bytes never enter it
  (protocol_enqueue_realtime_command / serial.c ISR).
- alarms: system_raise_alarm prints `ALARM:N`; critical ones (hard limit,
  soft limit, HAL e-stop; alarms.h alarm_is_critical) also print
  `[MSG:Reset to continue]` (HAL e-stop: its own message) and block until a
  reset: classic reads no lines at all then; HAL (protocol_poll_cmd) answers
  `$` commands marked allow_blocking and refuses the rest with error:79,
  G-code with error:9. After a reset in Alarm: `[MSG:'$H'|'$X' to unlock]`.
- reset (0x18, mc_reset): in Run/Jog/Homing or while a hold decelerates the
  position is lost: ALARM:3 (ALARM:6 when homing) is printed, then the
  banner (grbllib.c / main.c print it on every reset), then the unlock
  message. HAL ignores 0x18 while the e-stop input is active.
- holds: a feed hold or the door sets sys.suspend, and protocol_execute_realtime
  then runs protocol_exec_rt_suspend, which reads no line until the resume.
  Classic sets it only once the deceleration is over (protocol.c: EXEC_CYCLE_STOP
  with STEP_CONTROL_EXECUTE_HOLD sets SUSPEND_HOLD_COMPLETE): while it slows
  down the main loop still reads and plans lines and answers them `ok`. HAL sets
  it as the hold begins (state_machine.c initiate_hold: `sys.suspend = !sys.flags.soft_limit`).
- EEPROM and flash (`GrblConfig.storage_write`): classic writes `$x=` and G10
  L2/L20 before it answers, with its interrupts off, so bytes arriving then are
  lost (eeprom.c); HAL answers, then writes to flash once idle (protocol.c
  nvs_buffer_sync_physical) while its USB stack holds what arrives.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

from hostd.sim.config import AXES
from hostd.sim.gcode import Move
from hostd.sim.grbl import lines, motion_control, realtime, reports, system
from hostd.sim.grbl.codes import CRITICAL, Alarm, Error, Msg
from hostd.sim.grbl.config import GrblConfig
from hostd.sim.grbl.parser import Modal
from hostd.sim.grbl.reports import CLASSIC_VERSION, HAL_VERSION
from hostd.sim.grbl.settings import DEFAULTS, HAL_REPORT_MASK
from hostd.sim.motion import Active, Traversed
from hostd.sim.probing import ToolSensor, TouchPlate, probe_input, sensor_surface


class GrblBoard:
    """One grbl or grblHAL board; see the module docstring for how it is driven."""

    def __init__(
        self, config: GrblConfig, *, emit: Callable[[str], None], clock: Callable[[], float]
    ) -> None:
        self.config = config
        self.hal = config.hal
        self._emit = emit
        self._clock = clock
        # Inputs are wired to the machine: a reset keeps them.
        self.limits: set[str] = set()
        self.estop = False
        self.door_open = False
        self.probe = False
        # A fixed tool-length sensor (issue 29, probing.ToolSensor) and how much longer
        # than the first the tool in the spindle is: a G38.2 over the sensor trips itself.
        self.tool_sensor: ToolSensor | None = None
        self.tool_length = 0.0
        self.touch_plate: TouchPlate | None = None  # on the work, wired to the probe pin
        self.touch_reads = 0  # the operator holds the plate to the bit for this many `?`
        self.rx_dropped = 0  # bytes lost to a full receive ring, ever
        self.ovr_dropped = 0  # HAL: override bytes lost to a full override ring, ever
        self.lost_in_write = 0  # bytes lost while classic grbl wrote its EEPROM, ever
        self.status_lost = 0  # `?`s the wire is to lose next (line noise), as a test sets
        self.status_ignored = False  # `?` is not answered (reports stop), lines still are
        # Input waiting in the transport (`queue_input`): None reads as it arrives.
        self.queued: bytearray | None = None
        # The next G-code line is answered `error:N` with this code instead of run (a
        # test's: a code of a build, a setting or a machine the simulator lacks).
        self.refuse_next: int | None = None
        self.position = dict.fromkeys(AXES, 0.0)  # machine mm, survives a soft reset
        # `$N0`, `$N1` (N_STARTUP_LINE 2): kept in EEPROM, run after every reset (system.c).
        self.startup_lines = ["", ""]
        self.modal = Modal()
        self.homed = False
        self.alarm: Alarm | None = None
        self.state = "Idle"
        # Every move the machine made, in order (motion.Traversed), kept across resets.
        self.traversed: deque[Traversed] = deque(maxlen=config.history)
        # The spindle/laser output over time: (clock, S after overrides), one entry a change.
        self.beam: deque[tuple[float, float]] = deque([(0.0, 0.0)], maxlen=config.history)
        # Feed, rapid and spindle overrides after every main-loop pass that changed them.
        self.overrides_run: deque[tuple[int, int, int]] = deque(
            [(100, 100, 100)], maxlen=config.history
        )
        self.power_on()

    # --- power, reset

    def power_on(self) -> None:
        """A cold start: default settings, nothing homed, then what a reset does."""
        self.settings = dict(DEFAULTS)
        cfg = self.config
        self.settings[10] = HAL_REPORT_MASK if self.hal else 1
        self.settings[20] = int(cfg.soft_limits)
        self.settings[21] = int(cfg.hard_limits)
        self.settings[22] = int(cfg.homing) | (4 if cfg.homing_init_lock else 0)
        self.settings[32] = int(cfg.laser_mode)
        for i, travel in enumerate(cfg.max_travel):
            self.settings[130 + i] = travel
        for i in range(3):
            self.settings[110 + i] = cfg.rapid_rate
        self.position = dict.fromkeys(AXES, 0.0)
        # G54..G59 live in EEPROM (settings_write_coord_data): a power cycle keeps them.
        self.modal = Modal(wcs=self.modal.wcs) if hasattr(self, "modal") else Modal()
        self.homed = False
        self.alarm = None
        self.state = "Idle"
        self._cold = True
        self._init()
        self._startup()

    def _init(self) -> None:
        """grbllib.c / main.c's re-initialisation after power-on or a reset."""
        self.rx: deque[int] = deque()
        self._line = bytearray()
        self._overflow = False
        self._eol = 0
        self.last_error = Error.OK
        self.planner: deque[Move] = deque()
        self.active: Active | None = None
        self._jogging = False  # the planner holds a jog
        self._wait: motion_control.Wait | None = None
        self.hold = 0  # 0 none, 1 decelerating, 2 complete (HAL holding_state: Hold:n-1)
        self.door = 0  # parking_state while in Door
        self._cancel_after_stop = False  # jog cancel / classic hold in jog: flush when stopped
        self.blocking = False  # a critical alarm: only reset gets out
        self.feed_ovr = self.rapid_ovr = self.spindle_ovr = 100
        if self.overrides_run[-1] != (100, 100, 100):
            self.overrides_run.append((100, 100, 100))
        self.flood = self.mist = False
        self.modal.reset()
        self.modal.position = dict(self.position)
        self._status_pending = False
        self._deaf_until: float | None = None  # an EEPROM / flash write: no input till then
        self._held = bytearray()  # HAL: what arrived meanwhile, waiting in the USB stack
        self._nvs_dirty = False  # HAL: settings changed, written to flash once idle
        self._wco_counter = self._ovr_counter = 0  # report_init_message zeroes them
        self._report_flags: set[str] = {"overrides"}  # report_add_realtime(Report_Overrides)
        self._accessories_told = ""  # HAL: the accessories (`A:`) the last report said
        # `$481`'s next report, due whatever the host asks (GrblConfig.auto_report).
        every = self.config.auto_report
        self._auto_report_at = self._clock() + every if every else None

    def _startup(self) -> None:
        """The banner, then protocol_main_loop's start-up checks."""
        self._emit("")
        if self.hal:
            self._emit(f"GrblHAL {HAL_VERSION} ['$' or '$HELP' for help]")
        else:
            self._emit(f"Grbl {CLASSIC_VERSION} ['$' for help]")
        if self.hal and self.estop:
            self._raise(Alarm.ESTOP)
            self._message(Msg.ESTOP)
        elif self.hal and self._homing_required():
            self._raise(Alarm.HOMING_REQUIRED)
            self._message(Msg.HOMING_CYCLE_REQUIRED)
        elif (not self.hal and self._cold and self.settings[22]) or self.state in (
            "Alarm",
            "EStop",
        ):
            # Classic: HOMING_INIT_LOCK puts a homing machine in Alarm at power-up only.
            self.state = "Alarm"
            self._message(Msg.ALARM_LOCK)
        else:
            self.state = "Idle"
            if self.door_open:
                realtime.door_event(self)
            if self.state == "Idle":
                system.execute_startup(self)  # protocol.c: "All systems go!"
        self._cold = False

    def _bits(self, key: int) -> int:
        return int(self.settings[key])

    def _homing_required(self) -> bool:
        """HAL limits_homing_required(): homing on, init lock on, not homed."""
        return bool(self._bits(22) & 1) and bool(self._bits(22) & 4) and not self.homed

    def soft_reset(self) -> None:
        """0x18: mc_reset, then the re-initialisation (see the module docstring)."""
        if self.hal and self.estop:
            return  # protocol.c CMD_RESET: `if(!hal.control.get_state().e_stop) mc_reset()`
        now = self._clock()
        moving = self.state in ("Run", "Jog", "Home") or self.hold == 1
        if self.active is not None:
            self.position = self.active.position(now)
        if moving and not self.blocking:
            lost = Alarm.HOMING_FAIL_RESET if self.state == "Home" else Alarm.ABORT_CYCLE
            self.homed = False
            self._raise(lost, force=True)
        if self.state in ("Run", "Jog", "Home", "Hold", "Door", "Check", "Sleep"):
            self.state = "Idle"
        self._init()
        self._startup()

    # --- input: the serial interrupt

    def receive(self, data: bytes) -> None:
        """Bytes from the host: realtime ones act now (or after the read's report:
        `GrblConfig.report_first`), the rest queue or are lost.

        One read is one pass of the main loop for the overrides: those it brings
        act together (`realtime.overrides`: classic grbl's flag bits count two alike
        as one, grblHAL's rings drop what does not fit), after the read's report
        with `report_first`, else before a `?` behind them (it came a pass later).
        With `report_first` the `?`s of one read get one report: the interrupt sets one
        flag bit for them all (grblHAL protocol.c:871-875, EXEC_STATUS_REPORT; printed
        once a pass, :604-605)."""
        if self.queued is not None:
            self.queued += data  # it waits in the transport (`queue_input`)
            return
        if self._deaf_until is not None:
            if self.hal:
                self._held += data  # USB: the host's bytes wait until the write is over
            else:
                self.lost_in_write += len(data)  # the RX interrupt is off: overrun
            return
        capacity = self.config.rx_capacity
        # `GrblConfig.report_first`: the read's other realtime characters act after its
        # `?` is answered, in the order they came; a reset or a jog cancel at once, after
        # those before it.
        later: list[int] | None = [] if self.config.reports_first else None
        passing: list[int] = []  # this pass's override bytes
        reported = False  # with report_first: this pass's report is printed
        for byte in data:
            if byte == realtime.STATUS and (self.status_lost or self.status_ignored):
                self.status_lost = max(self.status_lost - 1, 0)
                continue
            if byte == realtime.STATUS and later is not None:
                if reported:
                    continue  # the flag is set already: one report for the pass
                reported = True
            if byte in realtime.OVERRIDES:
                passing.append(byte)
            elif byte in realtime.REALTIME:
                if byte == realtime.RESET:
                    # Lost: gnea/grbl main.c:84-85 clears the flags, grblHAL
                    # protocol.c:595 flushes the rings (flush_override_buffers).
                    passing.clear()
                    reported = False
                if later is None or byte == realtime.STATUS:
                    if later is None and byte == realtime.STATUS:
                        realtime.overrides(self, passing)
                        passing.clear()
                    self.realtime(byte)
                elif byte in (realtime.RESET, realtime.JOG_CANCEL):
                    self._act_on(later)
                    self.realtime(byte)
                else:
                    later.append(byte)
            elif byte >= 0x80 and self.hal:
                continue  # protocol_enqueue_realtime_command drops other top-bit bytes
            elif len(self.rx) >= capacity:
                self.rx_dropped += 1
            else:
                self.rx.append(byte)
        if later:
            self._act_on(later)
        realtime.overrides(self, passing)

    def queue_input(self, queued: bool) -> None:
        """While `queued`, what the host writes waits in the transport, unread; once off, it
        is read a byte at a time, in order, each byte its own read (one main-loop pass),
        as grblHAL's upstream Simulator feeds its firmware (grblHAL/Simulator c9f6b81
        src/mcu.c:291-305: one byte a pass, and only while the receive buffer has 100
        bytes free). A `?` queued behind others is answered by a report of its own, after
        the bytes before it acted, long after the host wrote it."""
        if queued:
            if self.queued is None:
                self.queued = bytearray()
            return
        waiting, self.queued = self.queued, None
        for byte in waiting or b"":
            self.receive(bytes((byte,)))

    def _act_on(self, later: list[int]) -> None:
        """The realtime characters kept back in this read, now, and forgotten."""
        for byte in later:
            self.realtime(byte)
        later.clear()

    @property
    def rx_free(self) -> int:
        """What `Bf:` reports as free receive buffer."""
        return self.config.rx_capacity - len(self.rx)

    def realtime(self, char: int) -> None:
        """A realtime character: acted on at once, never queued (realtime.py)."""
        realtime.command(self, char)

    # --- pins

    def set_limit(self, axis: str, active: bool) -> None:
        """A limit switch: with $21 on, triggering it is a hard limit (ALARM:1)."""
        if not active:
            self.limits.discard(axis)
            return
        self.limits.add(axis)
        if self.settings[21] and self.state not in ("Alarm", "EStop"):
            # machine_limits.c limit_interrupt_handler: mc_reset() then Alarm_HardLimit.
            motion_control.stop_motion(self)
            self.homed = False
            self._critical(Alarm.HARD_LIMIT)

    def set_estop(self, active: bool) -> None:
        """HAL e-stop input: ALARM:10 at once; reset is refused while it is held."""
        self.estop = active
        if active and self.hal and self.state != "EStop":
            motion_control.stop_motion(self)
            self.homed = False
            self._critical(Alarm.ESTOP)

    def set_door(self, active: bool) -> None:
        self.door_open = active
        if active and self.state != "Door":
            realtime.door_event(self)
        elif not active and self.state == "Door" and self.door == 1:
            self.door = 0  # EXEC_DOOR_CLOSED: ready to resume

    def probe_closed(self) -> bool:
        """probe_get_state(): the pin (a test's `probe`), a touch, or the plate at the bit."""
        return self.probe or self.touch_reads > 0 or self._touching(self.tool_position())

    def _touching(self, at: dict[str, float]) -> bool:
        """The bit at `at` touches the plate, or the tool sensor it stands over."""
        surface = sensor_surface(self.tool_sensor, self.tool_length, at)
        return probe_input(surface, self.touch_plate, at)

    def set_probe(self, active: bool) -> None:
        self.probe = active
        wait = self._wait
        if wait is not None and wait.kind == "probe" and wait.result is not None:
            probe = wait.result.probe
            if probe is not None and active == probe.toward and self.active is not None:
                motion_control.probe_contact(self)

    # --- the main loop

    def tick(self) -> bool:
        """Do one thing that is due; False when nothing is."""
        did = self._tick()
        self._note_beam()
        return did

    def beam_power(self) -> float:
        """The spindle output (a laser's power, S units) as the firmware drives it now.

        In laser mode ($32=1): off in a hold or at the door (config.h
        DISABLE_LASER_DURING_HOLD, protocol.c:536), and in a rapid; in a feed move the
        move's own S; standing still, M3 burns only while the motion mode is G1/G2/G3
        (gcode.c:868-893, 917-938) and M4 never does (spindle_control.c:252-253). Any
        alarm went through mc_reset, which stops the spindle. M5 is off.
        """
        laser = self.settings[32] == 1
        if self.state == "Alarm" or (laser and self.state in ("Hold", "Door")):
            return 0.0
        scale = self.spindle_ovr / 100.0
        active = self.active
        if active is not None and active.move is not None:
            move = active.move
            if move.spindle == "M5" or (laser and move.rapid):
                return 0.0
            return move.speed * scale
        modal = self.modal
        if modal.spindle == "M5":
            return 0.0
        if laser and (modal.spindle == "M4" or modal.motion not in (1.0, 2.0, 3.0)):
            return 0.0
        return modal.speed * scale

    def _note_beam(self) -> None:
        power = self.beam_power()
        if power != self.beam[-1][1]:
            self.beam.append((self._clock(), power))

    def _tick(self) -> bool:
        now = self._clock()
        if self._deaf_until is not None:
            if now < self._deaf_until:
                return False  # the CPU writes EEPROM or flash: nothing else runs
            self._deaf_until = None
            held, self._held = bytes(self._held), bytearray()
            self.receive(held)
            return True
        if self._auto_report_at is not None and now >= self._auto_report_at:
            self._auto_report_at = now + self.config.auto_report
            self._send_status()
            return True
        if motion_control.advance(self, now):
            return True
        if self.blocking:
            return self.hal and lines.read_line(self, critical=True)
        if self._suspended():
            return False
        if self._wait is not None:
            return motion_control.resume_wait(self, now)
        if self._nvs_dirty and self.state in ("Idle", "Alarm", "EStop"):
            self._nvs_dirty = False
            self._deaf_until = now + self.config.storage_write
            return True
        return lines.read_line(self, critical=False)

    def _suspended(self) -> bool:
        """protocol_exec_rt_suspend holds the main loop: no line is read (see above)."""
        if self.state == "Door":
            return True
        return self.state == "Hold" and (self.hal or self.hold == 2)

    def next_deadline(self) -> float | None:
        times: list[float] = []
        if self._deaf_until is not None:
            times.append(self._deaf_until)
        elif self._auto_report_at is not None:
            times.append(self._auto_report_at)
        if self.active is not None:
            times.append(self.active.end)
        if self._wait is not None and self._wait.kind in ("dwell", "home", "store"):
            times.append(self._wait.until)
        return min(times) if times else None

    def _stored(self, line: str) -> Error | None:
        """An EEPROM or flash write; the line's status, or None while classic writes."""
        seconds = self.config.storage_write
        if not seconds:
            return Error.OK
        if self.hal:
            self._nvs_dirty = True  # written once idle (nvs_buffer_sync_physical)
            return Error.OK
        until = self._clock() + seconds
        self._wait = motion_control.Wait("store", line, until=until)
        self._deaf_until = until
        return None

    # --- answers to lines (lines.py reads and runs them)

    def _respond(self, status: Error) -> None:
        self._emit("ok" if status == Error.OK else f"error:{int(status)}")

    def _done(self, status: Error = Error.OK) -> None:
        self._wait = None
        if self.hal:
            self.last_error = status
        self._respond(status)

    # --- alarms

    def _raise(self, alarm: Alarm, *, force: bool = False) -> None:
        """system_raise_alarm: print `ALARM:N` once per alarm and enter Alarm."""
        if self.alarm == alarm and not force and self.state in ("Alarm", "EStop"):
            return
        self.alarm = alarm
        self.state = "EStop" if alarm == Alarm.ESTOP else "Alarm"
        self._emit(f"ALARM:{int(alarm)}")

    def _critical(self, alarm: Alarm) -> None:
        self._raise(alarm, force=True)
        self._message(Msg.ESTOP if alarm == Alarm.ESTOP else Msg.CRITICAL_EVENT)
        self.blocking = alarm in CRITICAL
        self.rx.clear()  # hal.stream.reset_read_buffer(); classic stops reading
        self._line = bytearray()
        self._wait = None

    def _soft_limit(self) -> None:
        """limits_soft_check: hold, wait for standstill, reset, ALARM:2 (position kept)."""
        if self.active is not None:
            self.position = self.active.position(self._clock())
        motion_control.stop_motion(self)
        self._critical(Alarm.SOFT_LIMIT)

    # --- output

    def _message(self, msg: Msg) -> None:
        self._emit(f"[MSG:{msg.value}]")

    def _flush_status(self) -> None:
        if self._status_pending:
            self._status_pending = False
            self._send_status()

    def _send_status(self) -> None:
        self._emit(self.status_report())

    def tool_position(self) -> dict[str, float]:
        if self.active is not None:
            return self.active.position(self._clock())
        return dict(self.position)

    def status_report(self) -> str:
        """The status report `?` asks for (reports.py)."""
        return reports.status_report(self)

    def _state_text(self) -> str:
        return reports.state_text(self)
