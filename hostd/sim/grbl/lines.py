"""How the simulated grbl reads a line from its receive ring and runs it (protocol.c).

protocol_main_loop's part that takes bytes from the ring (board.py
`receive` fills it) up to a line end, drops what the firmware drops, and
runs the line: a `$` line through system.py, a G-code line through the
parser (parser.py) and, when it moves or waits, motion_control.py; then it
answers `ok` or `error:N`, unless the answer waits for the machine. Functions
that take the board, like the package's other modules; the board's main loop
(`GrblBoard._tick`) calls `read_line` when nothing else is due, with
`critical` while a critical alarm blocks (HAL protocol_poll_cmd).

- lines: protocol.c protocol_main_loop: CR or LF ends a line; an empty line
  answers `ok`; HAL skips the second byte of a CR LF pair unless the line
  before it failed (`eol = '\\0'`), classic answers it `ok` too. `$` lines go
  to system_execute_line; other lines in Alarm/E-stop/Jog answer error:9.
- HAL error latch (COMPATIBILITY_LEVEL 0): a G-code line runs only while
  gc_state.last_error is OK; otherwise it answers that same error. It is
  cleared by an empty line, by any `$` command (which sets it to its own
  result), and by 0x18 (the CAN read from the stream); 0x85 also cancels
  the read buffer, which inserts a CAN.
"""

from __future__ import annotations

from functools import partial
from typing import TYPE_CHECKING

from hostd.sim.grbl import motion_control, parser, system
from hostd.sim.grbl.codes import Error

if TYPE_CHECKING:
    from hostd.sim.grbl.board import GrblBoard

CLASSIC_LINE, HAL_LINE = 80, 257  # LINE_BUFFER_SIZE (protocol.h), one byte the terminator


def read_line(board: GrblBoard, *, critical: bool) -> bool:
    """Take bytes from the ring up to one complete line and run it."""
    if not board.rx:
        return False
    while board.rx:
        c = board.rx.popleft()
        if c in (0x0A, 0x0D):
            if board.hal and not board._line and board._eol and board._eol != c:
                board._eol = 0  # the second half of a CR LF pair
                continue
            board._eol = c
            line = board._line.decode("latin-1")
            overflow = board._overflow
            board._line = bytearray()
            board._overflow = False
            _run_line(board, line, overflow, critical=critical)
            return True
        if board.hal:
            if c <= (0x1F if board._line else 0x20) and c != 0x08:
                continue  # control characters and leading blanks
        elif c <= 0x20:
            continue  # classic drops every blank and control character
        limit = (HAL_LINE if board.hal else CLASSIC_LINE) - 1
        if len(board._line) >= limit:
            board._overflow = True
        else:
            board._line.append(c)
    return True


def _run_line(board: GrblBoard, line: str, overflow: bool, *, critical: bool) -> None:
    if critical:  # HAL protocol_poll_cmd, inside the critical-event loop
        if not line:
            status = Error.OK
        elif line.startswith("$"):
            answer = system.execute_line(board, line)
            status = Error.OK if answer is None else answer
        else:
            status = Error.SYSTEM_GC_LOCK
        board.last_error = status
        board._respond(status)
        return
    if overflow:
        status = Error.OVERFLOW
    elif not line:
        status = Error.OK
    elif line.startswith("$"):
        answer = system.execute_line(board, line)
        if answer is None:
            return  # the answer comes later (homing, a jog waiting for room)
        status = answer
    elif board.state in ("Alarm", "EStop", "Jog"):
        status = Error.SYSTEM_GC_LOCK
    elif board.hal and board.last_error != Error.OK:
        status = board.last_error  # the error latch
    elif board.refuse_next is not None:
        code, board.refuse_next = board.refuse_next, None
        board._emit(f"error:{code}")  # nothing latched, nothing run: the test's code only
        return
    else:
        result = _gcode(board, line)
        if result is None:
            return
        status = result
        if status != Error.OK:
            board._eol = 0
    if board.hal:
        board.last_error = status
    board._respond(status)


def _gcode(board: GrblBoard, line: str) -> Error | None:
    """gc_execute_block; None when the answer waits for the machine."""
    result = parser.execute(board.modal, line, travel_ok=partial(system.in_travel, board))
    if isinstance(result, Error):
        return result
    if result.offsets_changed:
        board._report_flags.add("wco")
        if not board.hal:  # classic: system_flag_wco_change (system.c): WCO next report
            board._wco_counter = 0
    if board.state == "Check":
        return Error.OK  # parsed, nothing moves (the parser's position moved on)
    for move in result.moves:
        if board.settings[20] and not system.in_travel(board, move.target):
            board._soft_limit()
            return None
    if result.moves or result.dwell is not None or result.probe or result.stop or result.stores:
        sync = result.dwell is not None or result.stop or result.stores
        kind = "room" if result.moves and not sync else "sync"
        board._wait = motion_control.Wait(kind, line, result)
        return None
    return Error.OK
