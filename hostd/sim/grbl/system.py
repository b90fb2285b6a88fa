"""The `$` commands (system.c system_execute_line): settings, `$X`, `$H`, `$C`, `$J=`.

`execute_line` runs one `$` line on a `GrblBoard` and gives its status, or
None when the answer comes later: the end of homing, a jog waiting for
planner room (motion_control.py), or `$C` leaving check mode, which answers
before the reset it causes. The reports it prints are made in reports.py.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import partial
from typing import TYPE_CHECKING

from hostd.sim.config import AXES
from hostd.sim.grbl import envelope, motion_control, parser, reports
from hostd.sim.grbl.codes import Error, Msg
from hostd.sim.grbl.settings import CLASSIC_FLAGS, FLOAT_SETTINGS, setting_text

if TYPE_CHECKING:
    from hostd.sim.grbl.board import GrblBoard

_NO_ANSWER: None = None


def execute_line(board: GrblBoard, line: str) -> Error | None:
    cmd, _, arg = line[1:].partition("=")
    cmd = cmd.replace(" ", "").upper()
    has_arg = "=" in line
    state = board.state
    if board.blocking and cmd not in ("G", "#", "$", "I", "N", "HELP", ""):
        # HAL: only commands flagged allow_blocking run during a critical event.
        return Error.NOT_ALLOWED_CRITICAL_EVENT
    if cmd == "":
        board._emit(reports.help_text(board))
        return Error.OK
    if cmd == "J" and has_arg:
        if state not in ("Idle", "Jog"):
            return Error.IDLE_ERROR
        return _jog(board, arg)
    if has_arg and cmd in ("G", "#", "$", "C", "X", "H", "I", "N"):
        return Error.INVALID_STATEMENT
    if cmd == "G":
        board._emit(reports.gc_modes(board))
        return Error.OK
    if cmd == "C":
        return _check_mode(board)
    if cmd == "X":
        return _unlock(board)
    if cmd == "H":
        return _home(board)
    if cmd == "$":
        if state in ("Run", "Hold"):
            return Error.IDLE_ERROR
        for key, value in sorted(board.settings.items()):
            board._emit(f"${key}={setting_text(key, value)}")
        return Error.OK
    idle = state in ("Idle", "Alarm") or (board.hal and state in ("EStop", "Check"))
    if cmd == "#":
        if not idle:
            return Error.IDLE_ERROR
        for text in reports.parameters(board):
            board._emit(text)
        return Error.OK
    if cmd == "I":
        # Only at rest: gnea/grbl system.c:172-175 (the IDLE/ALARM block, `$I` at :205);
        # grblHAL core system.c:635 build_info (Idle, Alarm, EStop, Sleep, Check).
        if not (idle or (board.hal and state == "Sleep")):
            return Error.IDLE_ERROR
        for text in reports.build_info(board):
            board._emit(text)
        return Error.OK
    if cmd == "N":
        if not idle:  # gnea/grbl system.c:237 (the IDLE/ALARM block); grblHAL :726
            return Error.IDLE_ERROR
        for n, text in enumerate(board.startup_lines):
            board._emit(f"$N{n}={text}")  # report_startup_line
        return Error.OK
    if cmd.startswith("N") and has_arg:
        return _store_startup(board, cmd[1:], arg)
    if cmd.isdigit():
        if not idle:
            return Error.IDLE_ERROR
        key = int(cmd)
        if key not in board.settings:
            return Error.INVALID_STATEMENT
        if not has_arg:
            board._emit(f"${key}={setting_text(key, board.settings[key])}")
            return Error.OK
        return _store(board, key, arg)
    return Error.INVALID_STATEMENT


def _store_startup(board: GrblBoard, number: str, block: str) -> Error | None:
    """`$Nn=block`: stored only in Idle, after the block ran once to prove it valid.

    system.c: "Execute gcode block to ensure block is valid": gc_execute_line runs it,
    moves and all, and only a block it accepts is stored.
    """
    if board.state != "Idle":
        return Error.IDLE_ERROR
    try:
        n = int(float(number))
    except ValueError:
        return Error.BAD_NUMBER_FORMAT
    if not 0 <= n < len(board.startup_lines):
        return Error.INVALID_STATEMENT
    text = block.replace(" ", "").upper()
    status = _run_block(board, text)
    if status is not Error.OK:
        return status
    board.startup_lines[n] = text
    return board._stored(f"$N{n}={text}")  # an EEPROM write, like a setting's


def execute_startup(board: GrblBoard) -> None:
    """system_execute_startup: each stored block runs, `>block:ok` (or its error) printed."""
    for text in board.startup_lines:
        if text:
            status = _run_block(board, text)
            answer = "ok" if status is Error.OK else f"error:{int(status)}"
            board._emit(f">{text}:{answer}")  # report_execute_startup_message


def _run_block(board: GrblBoard, text: str) -> Error:
    """gc_execute_line outside the serial stream: its moves are planned, nothing waits."""
    result = parser.execute(board.modal, text, travel_ok=partial(in_travel, board))
    if isinstance(result, Error):
        return result
    board.planner.extend(result.moves)
    return Error.OK


def _store(board: GrblBoard, key: int, raw: str) -> Error | None:
    try:
        value = float(raw)
    except ValueError:
        return Error.BAD_NUMBER_FORMAT
    if value < 0:
        return Error.NEGATIVE_VALUE
    if key == 20 and value and not board.settings[22]:
        return Error.SOFT_LIMIT_ERROR  # settings.c: soft limits need homing
    if not board.hal and key in CLASSIC_FLAGS:
        value = float(value != 0)  # a bit of settings.flags: `$$` says 0 or 1 (settings.c:243-296)
    if key == 22 and not value:
        # "Force disable soft-limits" (settings.c:279; HAL set_homing_enable).
        board.settings[20] = 0
    board.settings[key] = value if key in FLOAT_SETTINGS else int(value)
    return board._stored(f"${key}={raw}")


def _check_mode(board: GrblBoard) -> Error | None:
    if board.state == "Check":
        # system.c: leaving check mode is a reset; the `ok` goes out before the banner.
        board._message(Msg.DISABLED)
        board._respond(Error.OK)
        board.last_error = Error.OK
        board.state = "Idle"
        board._init()
        board._startup()
        return _NO_ANSWER
    if board.state != "Idle":
        return Error.IDLE_ERROR
    board.state = "Check"
    board._message(Msg.ENABLED)
    return Error.OK


def _unlock(board: GrblBoard) -> Error:
    if board.state not in ("Alarm", "EStop"):
        return Error.OK  # "Otherwise, no effect."
    if board.hal:
        if board.estop:
            return Error.ESTOP
        if board.door_open:
            return Error.CHECK_DOOR
        if board._homing_required():
            return Error.HOMING_REQUIRED
    elif board.door_open:
        return Error.CHECK_DOOR
    board.state = "Idle"
    board.alarm = None
    board._message(Msg.ALARM_UNLOCK)
    return Error.OK


def _home(board: GrblBoard) -> Error | None:
    if not board._bits(22) & 1:
        return Error.HOMING_DISABLED
    if board.state not in ("Idle", "Alarm"):
        return Error.IDLE_ERROR
    if board.door_open:
        return Error.CHECK_DOOR
    if board.hal and board.estop:
        return Error.ESTOP
    board.state = "Home"
    if board.hal and board.config.hal_home_report:
        board._send_status()  # mc_homing_cycle: "Force a status report" (COMPATIBILITY_LEVEL 0)
    cfg = board.config
    duration = 0.0 if cfg.instant else cfg.homing_time / cfg.speed_factor
    board._wait = motion_control.Wait("home", "$H", until=board._clock() + duration)
    return None


def _jog(board: GrblBoard, text: str) -> Error | None:
    result = parser.execute(board.modal, text, travel_ok=partial(_jog_travel_ok, board), jog=True)
    if isinstance(result, Error):
        return result
    if not result.moves:
        return Error.OK
    board._jogging = True
    board._wait = motion_control.Wait("room", "$J=" + text, result)
    return None


def _jog_travel_ok(board: GrblBoard, target: Mapping[str, float]) -> bool:
    return not board.settings[20] or in_travel(board, target)


def in_travel(board: GrblBoard, target: Mapping[str, float]) -> bool:
    """system_check_travel_limits, against `envelope`."""
    for i, axis in enumerate(AXES):
        low, high = envelope.envelope(board, i)
        if not low - 1e-6 <= target[axis] <= high + 1e-6:
            return False
    return True
