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
    elif char in FEED_OVR or char in RAPID_OVR or char in SPINDLE_OVR or char in COOLANT_OVR:
        _override(board, char)


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


def _override(board: GrblBoard, char: int) -> None:
    if char in FEED_OVR:
        steps = {0x90: None, 0x91: 10, 0x92: -10, 0x93: 1, 0x94: -1}
        step = steps[char]
        board.feed_ovr = 100 if step is None else min(max(board.feed_ovr + step, 10), 200)
    elif char in RAPID_OVR:
        board.rapid_ovr = {0x95: 100, 0x96: 50, 0x97: 25}[char]
    elif char == 0x9E:
        pass  # spindle stop: only in Hold with the spindle on; not modelled
    elif char in SPINDLE_OVR:
        steps = {0x99: None, 0x9A: 10, 0x9B: -10, 0x9C: 1, 0x9D: -1}
        step = steps[char]
        board.spindle_ovr = 100 if step is None else min(max(board.spindle_ovr + step, 10), 200)
    elif char == 0xA0:
        board.flood = not board.flood
    elif char == 0xA1:
        board.mist = not board.mist
    board._report_flags.add("overrides")
    board._ovr_counter = 0
