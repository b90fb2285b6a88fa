"""The realtime characters (grbl.h CMD_*) and what each does.

They never enter the receive ring: `GrblBoard.receive` hands each to
`command` as it arrives, whatever the main loop is doing. Status request,
feed hold, cycle start, safety door, jog cancel, the overrides and the
coolant toggles; 0x18 is the board's own soft reset.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from hostd.sim.grbl import motion_control
from hostd.sim.grbl.codes import Error, Msg

if TYPE_CHECKING:
    from hostd.sim.grbl.board import GrblBoard

# Realtime characters (grbl.h CMD_*).
RESET, STATUS, HOLD, CYCLE_START = 0x18, ord("?"), ord("!"), ord("~")
DOOR, JOG_CANCEL = 0x84, 0x85
FEED_OVR = range(0x90, 0x95)
RAPID_OVR = range(0x95, 0x98)
SPINDLE_OVR = range(0x99, 0x9F)
COOLANT_OVR = (0xA0, 0xA1)
OVERRIDES = frozenset({*FEED_OVR, *RAPID_OVR, *SPINDLE_OVR, *COOLANT_OVR})
# grblHAL's override rings: override.h OVERRIDE_BUFSIZE 16, and override.c:37-42 keeps a
# slot free (`bptr != feed.tail`), so 15 fit; a byte arriving at a full one is dropped.
HAL_RING = 15
REALTIME = frozenset(
    {RESET, STATUS, HOLD, CYCLE_START, DOOR, JOG_CANCEL, 0xA0, 0xA1}
    | set(FEED_OVR)
    | set(RAPID_OVR)
    | set(SPINDLE_OVR)
)


def command(board: GrblBoard, char: int) -> None:
    """Act on one realtime character, at once."""
    now = board._clock()
    if char == RESET:
        board.soft_reset()
    elif char == STATUS:
        board._status_pending = True
        if board.state != "Home":
            board._flush_status()
    elif char == HOLD:
        _feed_hold(board, now)
    elif char == CYCLE_START:
        _cycle_start(board)
    elif char == DOOR:
        if board.state != "Door":
            door_event(board)
    elif char == JOG_CANCEL:
        _jog_cancel(board, now)
    elif char in OVERRIDES:
        overrides(board, [char])


def _feed_hold(board: GrblBoard, now: float) -> None:
    state = board.state
    if state == "Jog":
        if not board.hal:
            _jog_cancel(board, now)  # classic: a hold during a jog cancels it
        return  # HAL state_set(STATE_HOLD): ignored while jogging
    if state in ("Alarm", "EStop", "Hold", "Door", "Sleep", "Home", "Check"):
        return
    board.state = "Hold"
    if board.active is not None and board.active.move is not None:
        board.active.begin_hold(now, board.config.feedhold_decel)
        board.hold = 1
    else:
        board.hold = 2  # nothing moving: the hold is complete at once


def _cycle_start(board: GrblBoard) -> None:
    if board.state == "Hold" and board.hold == 2:
        board.hold = 0
        board.modal.program_flow = ""  # M0 resumed
        board.state = "Run" if board.planner else "Idle"
    elif board.state == "Door" and board.door == 0 and board.active is None:
        board.state = "Run" if board.planner else "Idle"


def door_event(board: GrblBoard) -> None:
    """EXEC_SAFETY_DOOR: stop like a hold, into Door (state_machine.c / protocol.c)."""
    if board.state in ("Alarm", "EStop", "Sleep", "Check", "Home"):
        return
    board._message(Msg.SAFETY_DOOR_AJAR)
    if board.state == "Jog":
        _jog_cancel(board, board._clock())
    moving = board.active is not None and board.active.move is not None
    if moving and board.hold != 1:
        assert board.active is not None
        board.active.begin_hold(board._clock(), board.config.feedhold_decel)
    board.hold = 0
    board.state = "Door"
    board.door = 2 if moving else (1 if board.door_open else 0)


def _jog_cancel(board: GrblBoard, now: float) -> None:
    if board.hal:
        # CMD_JOG_CANCEL: hal.stream.cancel_read_buffer(), which queues a CAN: the
        # unread input and the line being assembled are gone, the latch is cleared.
        board.rx.clear()
        board._line = bytearray()
        board._overflow = False
        board.last_error = Error.OK
    if board.state != "Jog":
        return
    if board._wait is not None and board._wait.line.startswith("$J="):
        board._done()  # the jog line waiting for room is answered, not queued
    if board.active is not None and board.active.move is not None:
        if not board.active.decelerating:
            board.active.begin_hold(now, board.config.feedhold_decel)
        board._cancel_after_stop = True
    else:
        motion_control.flush_planner(board)
        board.state = "Idle"


def overrides(board: GrblBoard, chars: list[int]) -> None:
    """The override bytes that reached the board within one main-loop pass, in order.

    Classic grbl's receive interrupt only sets a flag bit per kind (serial.c:167-181,
    system.c:384-396) and protocol_exec_rt_system applies the flags once a pass
    (protocol.c:405-452): two "+10" in one pass are one. Its arithmetic is uint8_t,
    clamped after all the flags (protocol.c:411-417). grblHAL queues each byte in a
    ring of 15, feed and rapid sharing one, spindle and coolant one each
    (protocol.c:941-960, override.c:35-105), drops what finds its ring full, and
    applies every queued byte in the pass, clamping after each (protocol.c:631-722).
    Either reports `Ov:` in the next report only when a value changed (protocol.c:427,
    :452; grblHAL planner.c:782-787).
    """
    if not chars:
        return
    if board.hal:
        _hal_overrides(board, chars)
    else:
        _classic_overrides(board, set(chars))
    now = (board.feed_ovr, board.rapid_ovr, board.spindle_ovr)
    if now != board.overrides_run[-1]:
        board.overrides_run.append(now)
    # Coolant toggles: a flag bit each on classic grbl (once a pass), a ring on grblHAL.
    coolant = [c for c in chars if c in COOLANT_OVR]
    for char in set(coolant) if not board.hal else coolant[:HAL_RING]:
        if char == 0xA0:
            board.flood = not board.flood
        else:
            board.mist = not board.mist
    if coolant:
        _report_overrides(board)


def _classic_overrides(board: GrblBoard, flags: set[int]) -> None:
    feed, rapid = board.feed_ovr, board.rapid_ovr
    if 0x90 in flags:
        feed = 100
    for char, step in ((0x91, 10), (0x92, -10), (0x93, 1), (0x94, -1)):
        if char in flags:
            feed = (feed + step) & 0xFF  # uint8_t new_f_override
    feed = max(min(feed, 200), 10)
    for char, value in ((0x95, 100), (0x96, 50), (0x97, 25)):
        if char in flags:
            rapid = value
    if (feed, rapid) != (board.feed_ovr, board.rapid_ovr):
        board.feed_ovr, board.rapid_ovr = feed, rapid
        _report_overrides(board)
    spindle = board.spindle_ovr
    if 0x99 in flags:
        spindle = 100
    for char, step in ((0x9A, 10), (0x9B, -10), (0x9C, 1), (0x9D, -1)):
        if char in flags:
            spindle = (spindle + step) & 0xFF
    spindle = max(min(spindle, 200), 10)
    if spindle != board.spindle_ovr:
        board.spindle_ovr = spindle
        _report_overrides(board)
    # 0x9E, spindle stop: only in Hold with the spindle on; not modelled.


def _hal_overrides(board: GrblBoard, chars: list[int]) -> None:
    motion = [c for c in chars if c in FEED_OVR or c in RAPID_OVR]
    accessory = [c for c in chars if c in SPINDLE_OVR]
    board.ovr_dropped += max(len(motion) - HAL_RING, 0) + max(len(accessory) - HAL_RING, 0)
    feed, rapid = board.feed_ovr, board.rapid_ovr
    for char in motion[:HAL_RING]:
        if char == 0x90:
            feed = 100
        elif char in (0x91, 0x92, 0x93, 0x94):
            feed += {0x91: 10, 0x92: -10, 0x93: 1, 0x94: -1}[char]
        else:
            rapid = {0x95: 100, 0x96: 50, 0x97: 25}[char]
        feed = max(min(feed, 200), 10)
    if (feed, rapid) != (board.feed_ovr, board.rapid_ovr):
        board.feed_ovr, board.rapid_ovr = feed, rapid
        _report_overrides(board)
    spindle = board.spindle_ovr
    for char in accessory[:HAL_RING]:
        if char == 0x99:
            spindle = 100
        elif char != 0x9E:  # spindle stop: only in Hold with the spindle on; not modelled
            spindle += {0x9A: 10, 0x9B: -10, 0x9C: 1, 0x9D: -1}[char]
        spindle = max(min(spindle, 200), 10)
    if spindle != board.spindle_ovr:
        board.spindle_ovr = spindle
        _report_overrides(board)


def _report_overrides(board: GrblBoard) -> None:
    """`Ov:` in the next report (classic report_ovr_counter = 0; HAL Report_Overrides)."""
    board._report_flags.add("overrides")
    board._ovr_counter = 0
