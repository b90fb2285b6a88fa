"""How a simulated grbl board is built: which firmware, its buffers, its settings."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

Flavour = Literal["grbl", "grblhal"]

# gnea/grbl serial.h RX_BUFFER_SIZE and planner.h BLOCK_BUFFER_SIZE (16 slots, 15 usable).
CLASSIC_RX = 128
CLASSIC_BLOCKS = 15
# grblHAL/core stream.h RX_BUFFER_SIZE; config.h DEFAULT_PLANNER_BUFFER_BLOCKS ($398).
HAL_RX = 1024
HAL_BLOCKS = 100


@dataclass(frozen=True)
class GrblConfig:
    """A grbl 1.1h (`flavour="grbl"`) or grblHAL (`"grblhal"`) board.

    `rx_buffer` and `planner_blocks` default to the firmware's own (None):
    128 bytes and 15 blocks on grbl, 1024 and 100 on grblHAL. The settings
    below are the power-on values of `$20` (soft limits), `$21` (hard
    limits), `$22` (homing), `$32` (laser mode) and, on grblHAL, homing's
    init lock (`$22` bit 2: ALARM:11 until homed). Times are real seconds;
    `speed_factor` divides every move's duration, every dwell's and the homing cycle's
    (`homing_time`, in the machine's seconds), `instant` makes moves end at
    once. `reset_on_open`: opening the port resets the board, as an
    Arduino's DTR line does (None: True for grbl, False for grblHAL on
    native USB, which says nothing until spoken to).

    `hal_home_report`: grblHAL built with COMPATIBILITY_LEVEL 0 (the default)
    forces one `<Home|...>` report as a cycle starts (motion_control.c
    mc_homing_cycle); False is a build that prints none. `storage_write`:
    seconds an EEPROM or flash write keeps the board deaf (0: none). Classic
    grbl writes before it answers, with its interrupts off: bytes that arrive
    meanwhile are lost (eeprom.c eeprom_put_char's cli(); about 0.3 s for a
    `$x=`). grblHAL answers first and writes its settings to flash once idle
    (protocol.c nvs_buffer_sync_physical): bytes wait in the USB stack.

    `line_numbers`: classic grbl built with USE_LINE_NUMBERS (gnea/grbl
    config.h:159, off by default): `[OPT:]` then says `N` (report.c:379-381)
    and a status report carries `Ln:` (report.c:540-548). Without it the
    board parses a line's N word and keeps none of it (gcode.c:309 and
    :902-905). grblHAL always does both (grblHAL/core report.c:897 and the
    report's `Ln:`, :1314-1319), whatever this says.

    `report_first`: realtime characters that arrive in one read with a `?` act
    after the report is printed, as the firmware's main loop takes them: the
    receive interrupt only raises flags (gnea/grbl serial.c ISR(SERIAL_RX),
    grblHAL protocol.c protocol_enqueue_realtime_command) and
    protocol_exec_rt_system prints the status report before it runs a hold, a
    cycle start, a door or an override (gnea/grbl protocol.c:250-253 then
    :405-478; grblHAL protocol.c:604-605 then :624-735). None: True for
    grblHAL, whose native USB hands the firmware a whole packet in one go;
    False for grbl, whose UART brings a byte at a time (87 us apart at 115200
    baud), so each is acted on as it arrives. Reset and jog cancel act at once
    either way (mc_reset and cancel_read_buffer run in the interrupt).

    `auto_report`: grblHAL's `$481`, in seconds (0: off, its default,
    config.h DEFAULT_AUTOREPORT_INTERVAL): a status report every so often that
    no `?` asked for (grbllib.c:160-167 sets EXEC_STATUS_REPORT from a delayed
    task). A `?` is still answered besides (protocol.c:987-990; only 0x80 is
    ignored while auto-reporting, :871-875). The firmware takes 100 to 1000 ms
    (settings.c:2449); tests may take less.
    """

    flavour: Flavour = "grbl"
    rx_buffer: int | None = None
    planner_blocks: int | None = None
    soft_limits: bool = False
    hard_limits: bool = False
    homing: bool = False
    homing_init_lock: bool = False
    laser_mode: bool = False
    max_travel: tuple[float, float, float] = (200.0, 200.0, 200.0)  # $130-$132, mm
    speed_factor: float = 1.0
    instant: bool = False
    rapid_rate: float = 500.0  # mm/min, $110-$112 (the firmware defaults)
    homing_time: float = 0.05  # s a homing cycle takes (divided by speed_factor)
    hal_home_report: bool = True
    storage_write: float = 0.0
    feedhold_decel: float = 0.05  # s from `!` to standing still
    reset_on_open: bool | None = None
    report_first: bool | None = None
    line_numbers: bool = False
    auto_report: float = 0.0
    history: int | None = None  # entries kept in `received` / `sent`; None keeps all

    def __post_init__(self) -> None:
        if self.flavour not in ("grbl", "grblhal"):
            raise ValueError(f"flavour is 'grbl' or 'grblhal', not {self.flavour!r}")
        if self.rx_buffer is not None and not 16 <= self.rx_buffer <= 65536:
            raise ValueError("rx_buffer must be 16..65536 bytes")
        if self.planner_blocks is not None and self.planner_blocks < 1:
            raise ValueError("planner_blocks must be at least 1")
        if self.speed_factor <= 0:
            raise ValueError("speed_factor must be positive")
        if self.storage_write < 0 or self.homing_time < 0:
            raise ValueError("storage_write and homing_time are seconds, not negative")
        if self.homing_init_lock and self.flavour != "grblhal":
            raise ValueError("homing_init_lock (ALARM:11) is a grblHAL setting")
        if self.auto_report < 0 or (self.auto_report and self.flavour != "grblhal"):
            raise ValueError("auto_report ($481) is a grblHAL setting, in seconds, not negative")

    @property
    def hal(self) -> bool:
        return self.flavour == "grblhal"

    @property
    def reports_lines(self) -> bool:
        """`[OPT:]` says `N` and a status report carries `Ln:`."""
        return self.hal or self.line_numbers

    @property
    def rx_size(self) -> int:
        """What [OPT:] reports as the receive buffer size."""
        if self.rx_buffer is not None:
            return self.rx_buffer
        return HAL_RX if self.hal else CLASSIC_RX

    @property
    def rx_capacity(self) -> int:
        """Bytes the ring really holds before it drops one.

        grbl's ring has RX_BUFFER_SIZE+1 slots (serial.c RX_RING_BUFFER), so
        it holds all 128; grblHAL's drivers use RX_BUFFER_SIZE slots and
        `next_head == tail` means full, so one fewer.
        """
        return self.rx_size - 1 if self.hal else self.rx_size

    @property
    def blocks(self) -> int:
        if self.planner_blocks is not None:
            return self.planner_blocks
        return HAL_BLOCKS if self.hal else CLASSIC_BLOCKS

    @property
    def reports_first(self) -> bool:
        return self.hal if self.report_first is None else self.report_first

    @property
    def opens_with_reset(self) -> bool:
        return (not self.hal) if self.reset_on_open is None else self.reset_on_open
