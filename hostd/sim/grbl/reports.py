"""What the simulated grbl prints about itself (report.c): `?`, `$G`, `$#`, `$I`, `$`.

Functions of a `GrblBoard`'s state that return text; the board emits it.
Only the status report changes anything: it advances the refresh counters of
`WCO:` and `Ov:` (and clears the board's report flags) as report.c does.

- states and substates: report.c report_realtime_status; state_machine.c
  (HAL Door:0 closed, 1 ajar, 2 retracting, 4 resuming; classic 3 restoring).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from hostd.sim.config import AXES
from hostd.sim.grbl import envelope, parser
from hostd.sim.grbl.parser import MM_PER_INCH

if TYPE_CHECKING:
    from hostd.sim.grbl.board import GrblBoard

CLASSIC_VERSION, CLASSIC_BUILD = "1.1h", "20190830"  # gnea/grbl grbl.h
HAL_VERSION, HAL_BUILD = "1.1f", "20260817"  # grblHAL/core grbl.h
WCO_BUSY, WCO_IDLE, OVR_BUSY, OVR_IDLE = 30, 10, 20, 10  # REPORT_*_REFRESH_*_COUNT
BUSY_STATES = frozenset({"Home", "Run", "Hold", "Jog", "Door"})


def status_report(board: GrblBoard) -> str:
    """report.c report_realtime_status, field by field."""
    now = board._clock()
    mask = int(board.settings[10])
    mpos = board.tool_position()
    wco = board.modal.wco()
    state = state_text(board)
    fields = [state]
    ins = inches(board)
    if mask & 1:
        fields.append(f"MPos:{axes(mpos, ins)}")
    else:
        fields.append(f"WPos:{axes({a: mpos[a] - wco[a] for a in AXES}, ins)}")
    if mask & 2:
        free = board.config.blocks - len(board.planner)
        fields.append(f"Bf:{max(free, 0)},{board.rx_free}")
    # report.c: the N of plan_get_current_block(), the block executing or next to
    # (it may not have started: grbl says Idle for an instant before a cycle); with
    # the planner empty grblHAL reports the parser's last N, classic grbl nothing.
    # Classic grbl prints it only when built with USE_LINE_NUMBERS (config.py).
    line = board.planner[0].n if board.planner else 0
    if board.hal and not board.planner:
        line = board.modal.line
    if line and board.config.reports_lines:
        fields.append(f"Ln:{line}")
    rate = board.active.velocity(now) if board.active is not None else 0.0
    speed = board.modal.speed * board.spindle_ovr / 100 if board.modal.spindle != "M5" else 0.0
    if ins:  # printFloat_RateValue: in/min to 1 place
        fields.append(f"FS:{rate / MM_PER_INCH:.1f},{speed:.0f}")
    else:
        fields.append(f"FS:{rate:.0f},{speed:.0f}")
    pins = _pins(board)
    if board.touch_reads:
        board.touch_reads -= 1  # the operator saw it read and lets go
    if pins:
        fields.append(f"Pn:{pins}")
    if board.hal:
        fields.extend(_hal_tail(board))
    else:
        fields.extend(_classic_tail(board, wco))
    return "<" + "|".join(fields) + ">"


def state_text(board: GrblBoard) -> str:
    state = board.state
    if state == "Hold":
        # classic: 0 ready to resume, 1 holding; HAL holding_state - 1, the same numbers.
        return "Hold:0" if board.hold == 2 else "Hold:1"
    if state == "Door":
        return f"Door:{board.door}"
    if state == "EStop":
        return "Alarm"
    return state


def _pins(board: GrblBoard) -> str:
    limits = "".join(a.upper() for a in AXES if a in board.limits)
    if not board.hal:  # classic order: P, XYZ, then D R H S
        return ("P" if board.probe_closed() else "") + limits + ("D" if board.door_open else "")
    # HAL: limits, then control signals in bit order "RHSDLTEOFM Q  P ".
    ctrl = ("D" if board.door_open else "") + ("E" if board.estop else "")
    return limits + ctrl + ("P" if board.probe_closed() else "")


def _classic_tail(board: GrblBoard, wco: dict[str, float]) -> list[str]:
    """gnea/grbl: WCO every 10 (idle) or 30 (busy) reports, Ov the report after."""
    out: list[str] = []
    busy = board.state in BUSY_STATES
    if board._wco_counter > 0:
        board._wco_counter -= 1
    else:
        board._wco_counter = (WCO_BUSY if busy else WCO_IDLE) - 1
        if board._ovr_counter == 0:
            board._ovr_counter = 1
        out.append(f"WCO:{axes(wco, inches(board))}")
    if board._ovr_counter > 0:
        board._ovr_counter -= 1
    else:
        board._ovr_counter = (OVR_BUSY if busy else OVR_IDLE) - 1
        out.append(f"Ov:{board.feed_ovr},{board.rapid_ovr},{board.spindle_ovr}")
        accessories = _accessories(board)
        if accessories:
            out.append(f"A:{accessories}")
    return out


def _hal_tail(board: GrblBoard) -> list[str]:
    """grblHAL: Ov when its counter runs out or flagged; WCO likewise but never in the
    same report as Ov unless forced (it is then flagged for the next report)."""
    flags = board._report_flags
    busy = board.state in BUSY_STATES
    overrides = board._ovr_counter == 0 or "overrides" in flags
    if overrides:
        board._ovr_counter = (OVR_BUSY if busy else OVR_IDLE) - 1
    else:
        board._ovr_counter -= 1
    if board._ovr_counter > OVR_IDLE - 1 and board.state == "Idle":
        board._ovr_counter = OVR_IDLE - 1
    wco = delayed_wco = False
    if board._wco_counter == 0 or "wco" in flags:
        board._wco_counter = (WCO_BUSY if busy else WCO_IDLE) - 1
        wco = not overrides
        delayed_wco = not wco
    else:
        board._wco_counter -= 1
    if board._wco_counter > WCO_IDLE - 1 and board.state == "Idle":
        board._wco_counter = WCO_IDLE - 1
    out: list[str] = []
    if wco:
        out.append(f"WCO:{axes(board.modal.wco(), inches(board))}")
    if overrides:
        out.append(f"Ov:{board.feed_ovr},{board.rapid_ovr},{board.spindle_ovr}")
    # A: on the report after the spindle or coolant changes, whatever it says, even none
    # (spindle_control.c:750 and coolant_control.c:37 `report_add_realtime`, report.c:
    # 1475-1505), and with an Ov refresh while any is on (report.c:1419-1420).
    accessories = _accessories(board)
    if accessories != board._accessories_told or (overrides and accessories):
        out.append(f"A:{accessories}")
        board._accessories_told = accessories
    if "homed" in flags and board._bits(22) & 1:
        out.append(f"H:{int(board.homed)}")
    board._report_flags = {"wco"} if delayed_wco else set()
    return out


def _accessories(board: GrblBoard) -> str:
    spindle = {"M3": "S", "M4": "C"}.get(board.modal.spindle, "")
    flood = "F" if board.flood or "M8" in board.modal.coolant else ""
    mist = "M" if board.mist or "M7" in board.modal.coolant else ""
    return spindle + flood + mist


def gc_modes(board: GrblBoard) -> str:
    """report_gcode_modes: `[GC:...]`."""
    m = board.modal
    motion = {0.0: "G0", 1.0: "G1", 2.0: "G2", 3.0: "G3", 80.0: "G80"}.get(
        m.motion, f"G{m.motion:g}"
    )
    parts = [motion, f"G{54 + m.coord}"]
    if board.hal and any(m.g92.values()):
        parts.append("G92")
    parts += [f"G{m.plane}", "G21" if m.metric else "G20", "G90" if m.absolute else "G91"]
    parts.append("G93" if m.inverse_time else "G94")
    if board.hal:
        parts += ["G40", "G49", "G98", "G50"]
    if m.program_flow:
        parts.append(m.program_flow)
    parts.append(m.spindle)
    if m.coolant:
        parts += sorted(m.coolant)
    else:
        parts.append("M9")
    feed = m.feed if m.metric else m.feed / parser.MM_PER_INCH
    parts += [f"T{m.tool}", f"F{feed:.0f}", f"S{m.speed:.0f}"]
    return "[GC:" + " ".join(parts) + "]"


def parameters(board: GrblBoard) -> list[str]:
    """report_ngc_parameters: `$#`."""
    m = board.modal
    ins = inches(board)
    out = [f"[G{54 + i}:{axes(m.wcs[i], ins)}]" for i in range(6)]
    zero = dict.fromkeys(AXES, 0.0)
    out += [f"[G28:{axes(zero, ins)}]", f"[G30:{axes(zero, ins)}]", f"[G92:{axes(m.g92, ins)}]"]
    if board.hal and board._bits(22) & 1:
        home = {
            axis: envelope.home_position(board, i) if board.homed else 0.0
            for i, axis in enumerate(AXES)
        }
        out.append(f"[HOME:{axes(home, ins)}:{7 if board.homed else 0}]")
    out.append("[TLO:0.000]")
    out.append(f"[PRB:{axes(m.probe, ins)}:{int(m.probe_ok)}]")
    return out


def build_info(board: GrblBoard) -> list[str]:
    """report_build_info: `$I`."""
    if not board.hal:
        return [
            f"[VER:{CLASSIC_VERSION}.{CLASSIC_BUILD}:]",
            f"[OPT:V{'N' if board.config.line_numbers else ''},"
            f"{board.config.blocks},{board.config.rx_size}]",
        ]
    opt = "VNM" + ("" if board._bits(22) & 4 else "L") + "+"
    newopt = "ENUMS,RT+," + ("HOME," if board._bits(22) & 1 else "") + "ES,SED"
    return [
        f"[VER:{HAL_VERSION}.{HAL_BUILD}:]",
        f"[OPT:{opt},{board.config.blocks},{board.config.rx_size},3,0]",
        "[AXS:3:XYZ]",
        f"[NEWOPT:{newopt}]",
        "[FIRMWARE:grblHAL]",
    ]


def help_text(board: GrblBoard) -> str:
    if board.hal:
        return "[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H $B ~ ! ? ctrl-x]"
    return "[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]"


def axes(values: dict[str, float], inches: bool = False) -> str:
    """report_util_axis_values / printFloat_CoordValue: mm to 3 places, or with `$13=1`
    inches to 4 (gnea/grbl report.c, N_DECIMAL_COORDVALUE_INCH)."""
    if inches:
        return ",".join(f"{values[a] / MM_PER_INCH:.4f}" for a in AXES)
    return ",".join(f"{values[a]:.3f}" for a in AXES)


def inches(board: GrblBoard) -> bool:
    """`$13` (report inches): positions and rates in inches, whatever G20 or G21 says."""
    return bool(board._bits(13) & 1)
