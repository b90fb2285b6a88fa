"""Motion without the hardware: the planner's blocks, and what a line waits for.

The parts of motion_control.c, planner.c and stepper.c that the board needs:
`advance` runs the planner's blocks one at a time on the board's clock
(hostd/sim/motion.py moves the tool); `resume_wait` answers the line being
executed once what it waits for has happened: planner room, the planner
empty, a dwell, the homing cycle, a probe cycle.

- planner: a line whose block finds the planner full waits (mc_line loops on
  plan_check_full_buffer), and its `ok` comes once it is queued;
  `[OPT:]` / `Bf:` give BLOCK_BUFFER_SIZE-1 (classic) or $398 (HAL) blocks.
- homing: motion_control.c mc_homing_cycle: HAL forces one status report as
  homing starts; `?` is not serviced during the cycle (limits_go_home only
  looks at reset/door; $10 bit "report when homing" is off by default), so a
  `?` sent then is answered once, when the cycle ends. HAL prints `[MSG:]`
  after a successful `$H` (feedback_message(Message_None)).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

from hostd.sim.config import AXES
from hostd.sim.gcode import Move
from hostd.sim.grbl import envelope, reports
from hostd.sim.grbl.codes import Alarm, Msg
from hostd.sim.grbl.parser import Executed, Probe
from hostd.sim.motion import Active, Traversed, start_block
from hostd.sim.probing import contact, sensor_surface

if TYPE_CHECKING:
    from hostd.sim.grbl.board import GrblBoard


@dataclass
class Wait:
    """What the line being executed waits for before its response (None: nothing)."""

    kind: str  # "room", "sync", "dwell", "home", "probe", "store"
    line: str
    result: Executed | None = None
    until: float = 0.0
    tripped: bool = False  # a probe move that ends where the touch plate trips it


def advance(board: GrblBoard, now: float) -> bool:
    """Motion: finish the running block, start the next, settle states."""
    active = board.active
    if active is not None:
        if now < active.end:
            return False
        if active.decelerating:
            _stopped(board, now)
        else:
            _finish(board, active)
        return True
    if board.blocking or board.state in ("Alarm", "EStop", "Home", "Sleep"):
        return False
    if board.hold or board.state == "Door":
        return False
    if board.planner:
        _start(board, now)
        return True
    if board.state in ("Run", "Jog"):
        board.state = "Idle"
        board._jogging = False
        return True
    return False


def _start(board: GrblBoard, now: float) -> None:
    move = board.planner[0]
    board.traversed.append(Traversed(dict(board.position), move, board.settings[32] == 1))
    if not move.rapid and board.feed_ovr != 100:
        move = replace(move, feed=move.feed * board.feed_ovr / 100)
    board.active = start_block(
        move,
        board.position,
        now,
        speed_factor=board.config.speed_factor,
        rapid_rate=board.settings[110] * board.rapid_ovr / 100,
        instant=board.config.instant,
    )
    board.active.block = board.planner[0]
    board.state = "Jog" if board._jogging else "Run"


def _finish(board: GrblBoard, active: Active) -> None:
    board.active = None
    if active.move is not None:
        board.position = dict(active.move.target)
    if board.planner:
        board.planner.popleft()
    if board._wait is not None and board._wait.kind == "probe":
        _probe_end(board, contact=board._wait.tripped)


def _stopped(board: GrblBoard, now: float) -> None:
    """A hold's deceleration reached standstill (EXEC_CYCLE_STOP)."""
    active = board.active
    assert active is not None
    board.position = active.position(active.end)
    rest = active.rest(active.end)
    board.active = None
    if board.planner:
        board.planner.popleft()
        if isinstance(rest, Move):
            board.planner.appendleft(rest)
    if board._cancel_after_stop:
        board._cancel_after_stop = False
        flush_planner(board)
        board.hold = 0
        board.state = "Idle"
        return
    if board.state == "Door":
        board.door = 1 if board.door_open else 0
    else:
        board.hold = 2


def resume_wait(board: GrblBoard, now: float) -> bool:
    wait = board._wait
    assert wait is not None
    result = wait.result
    if wait.kind == "room":
        if len(board.planner) >= board.config.blocks:
            return False
        assert result is not None
        board.planner.extend(result.moves)
        board._done()
        return True
    if wait.kind == "sync":
        if board.planner or board.active is not None or board.hold or board.state == "Door":
            return False
        assert result is not None
        return _after_sync(board, result, now)
    if wait.kind in ("dwell", "home", "store"):
        if now < wait.until:
            return False
        if wait.kind == "home":
            homed(board)
        else:
            board._done()
        return True
    return False  # a probe ends from motion or the probe pin


def _after_sync(board: GrblBoard, result: Executed, now: float) -> bool:
    wait = board._wait
    assert wait is not None
    if result.dwell is not None:
        wait.kind = "dwell"
        # In the board's time, as a move's (`speed_factor`; the g2core simulator's too).
        wait.until = now + (
            0.0 if board.config.instant else result.dwell / board.config.speed_factor
        )
        return True
    if result.probe is not None:
        return _probe_start(board, result.probe, now)
    if result.stores:
        # settings.c settings_write_coord_data: FORCE_BUFFER_SYNC_DURING_EEPROM_WRITE
        # synced the planner (this wait), then the write.
        answer = board._stored(wait.line)
        if answer is not None:
            board._done(answer)
        return True
    if result.stop in ("M2", "M30"):
        board._message(Msg.PROGRAM_END)
    elif result.stop == "M0":
        board.hold = 2
        board.state = "Hold"
    board._done()
    return True


def homed(board: GrblBoard) -> None:
    board.position = {axis: envelope.home_position(board, i) for i, axis in enumerate(AXES)}
    board.modal.position = dict(board.position)
    board.homed = True
    if board._status_pending:
        board._flush_status()  # the `?` that waited out the cycle, still in Home
    board.state = "Idle"
    board.alarm = None
    board._report_flags.add("homed")
    if board.hal:
        board._message(Msg.NONE)
    board._done()


def stop_motion(board: GrblBoard) -> None:
    now = board._clock()
    if board.active is not None:
        board.position = board.active.position(now)
        board.active = None
    flush_planner(board)
    board._wait = None
    board.hold = 0


def flush_planner(board: GrblBoard) -> None:
    board.planner.clear()
    board._jogging = False
    board.modal.position = dict(board.position)


# Probing (motion_control.c mc_probe_cycle).


def _probe_start(board: GrblBoard, probe: Probe, now: float) -> bool:
    # mc_probe_cycle: "check if probe is already triggered" (probe_get_state) after
    # the sync, ALARM:4 (EXEC_ALARM_PROBE_FAIL_INITIAL) and GC_PROBE_FAIL_INIT.
    if board.probe_closed() == probe.toward:
        board._raise(Alarm.PROBE_FAIL_INITIAL)
        board._done()
        return True
    # The touch plate: the move ends where the bit meets it (the stepper ISR's
    # probe_state_monitor copies sys_position into sys_probe_position and stops).
    # The tool sensor (issue 29), where the bit stands over it, likewise.
    surface = sensor_surface(board.tool_sensor, board.tool_length, board.position)
    trip = contact(surface, board.touch_plate, board.position, probe.move.target, probe.toward)
    board.planner.append(probe.move if trip is None else replace(probe.move, target=trip))
    board._wait = Wait("probe", "", _probe_result(probe), tripped=trip is not None)
    _start(board, now)
    return True


def probe_contact(board: GrblBoard) -> None:
    active = board.active
    assert active is not None
    board.position = active.position(board._clock())
    board.active = None
    board.planner.clear()
    _probe_end(board, contact=True)


def _probe_end(board: GrblBoard, *, contact: bool) -> None:
    wait = board._wait
    assert wait is not None and wait.result is not None and wait.result.probe is not None
    board.state = "Idle"
    board.modal.position = dict(board.position)
    board.modal.probe_ok = contact
    # mc_probe_cycle: classic keeps the position on a touch or where a G38.3/.5 ended,
    # and a G38.2/.4 that missed keeps the last touch's (gnea motion_control.c:296-298);
    # HAL keeps where the cycle ended either way (grblHAL motion_control.c:1104-1107).
    if contact or board.hal or not wait.result.probe.fail_alarm:
        board.modal.probe = dict(board.position)
    if not contact and wait.result.probe.fail_alarm:
        board._raise(Alarm.PROBE_FAIL_CONTACT)
    probe = reports.axes(board.modal.probe, reports.inches(board))
    board._emit(f"[PRB:{probe}:{int(board.modal.probe_ok)}]")
    board._done()


def _probe_result(probe: Probe) -> Executed:
    return Executed(probe=probe)
