"""The resume plan, line by line, for the resumes that went wrong (issue 24).

Each case is a file as a shop writes it, and a board holding its stored offsets.
The plan's lines are run through the modal model from the board's state (a
freshly reset board: its stored G54.. kept, G92 gone), and the tool must end
where the file had it, in machine coordinates, with the file's modes. The
whole path against the simulated boards is in tests/daemon/test_resume_safety.py.
"""

from __future__ import annotations

import pytest

from hostd.protocol.g2core import G2Session
from hostd.protocol.gcodestate import G2CORE, GRBL, Dialect, GcodeModel
from hostd.protocol.gcodestate.resume import Board, ResumeError, ResumePlan, plan_resume
from hostd.protocol.gcodestate.state import AXES
from hostd.protocol.grbl.session import GrblSession

ZERO = dict.fromkeys(AXES, 0.0)
# A machine whose G54 is 100, 100, -80 from machine zero (the stock's top is work Z0).
OFFSETS = {"G54": {**ZERO, "x": 100.0, "y": 100.0, "z": -80.0}, "G55": ZERO}
BOARD = Board(OFFSETS)


def _plan(text: str, line: int, dialect: Dialect = G2CORE, **kw: object) -> ResumePlan:
    args: dict[str, object] = {"board": BOARD, "safe_z": -2.0, "dwell": 1.0} | kw
    return plan_resume(text.splitlines(), line, dialect, **args)  # type: ignore[arg-type]


def _after(lines: list[str], board: Board, dialect: Dialect = G2CORE) -> GcodeModel:
    """The model after `lines`, on a board that holds `board` and stands at machine 0."""
    model = GcodeModel(dialect, start=ZERO, offsets=board.offsets, g92=board.g92)
    return model.feed_lines(lines)


def _file_at(text: str, line: int, board: Board, dialect: Dialect = G2CORE) -> GcodeModel:
    return _after(text.splitlines()[: line - 1], board, dialect)


def _machine(model: GcodeModel) -> tuple[float, ...]:
    return tuple(round(v, 3) for v in model.pos[:3])


G53_RETRACT = """\
G21 G90 G54 G17
G0 Z5
G0 X10 Y10
S12000 M3
G1 Z-1 F300
G1 X60 F1500
G53 G0 Z-1
G0 X10 Y40
G1 Z-1 F300
G1 X60 F1500
"""


def test_after_a_g53_retract_the_tool_arrives_where_the_retract_left_it() -> None:
    plan = _plan(G53_RETRACT, 8)
    # The file's retract: machine Z -1, which is work Z 79. Before the fix the approach
    # read it as work Z -1 and went down 80 mm, 1 mm into the stock.
    assert plan.machine == {"x": 160.0, "y": 110.0, "z": -1.0}
    assert plan.position == {"x": 60.0, "y": 10.0, "z": 79.0}
    ran = _after(plan.lines, BOARD)
    assert _machine(ran) == _machine(_file_at(G53_RETRACT, 8, BOARD)) == (160.0, 110.0, -1.0)
    assert all("G53" in text for text in plan.approach if text.startswith(("G90", "G53")))


G10_L20 = """\
G21 G90 G54
G0 Z5
G0 X50 Y50
G10 L20 P2 X0 Y0 Z0
G55
S9000 M3
G1 Z-1 F300
G1 X20 F1200
G1 Y20
"""


def test_a_g10_in_the_file_is_never_written_and_is_said() -> None:
    # The job ran line 4: the board stored G55 = where the tool stood then (machine 150,
    # 150, -75). The preamble used to write G55 from the file with its offsets taken as
    # zero, moving G55 200 mm away.
    stored = Board({**OFFSETS, "G55": {**ZERO, "x": 150.0, "y": 150.0, "z": -75.0}})
    plan = _plan(G10_L20, 9, board=stored)
    assert not any(text.startswith("G10") or " G10" in text for text in plan.lines)
    said = [t for t in plan.uncertain if "G55" in t and "G10" in t]
    assert said and "line 4" in said[0] and "X 150, as the file wrote" in said[0]
    ran = _after(plan.lines, stored)
    assert _machine(ran) == _machine(_file_at(G10_L20, 9, stored)) == (170.0, 150.0, -76.0)
    # A board that holds another G55 (changed since, or the job never got to line 4):
    # the plan still uses the board's, the one the file's next lines will run in, and
    # says where it differs.
    moved = Board({**OFFSETS, "G55": {**ZERO, "x": 150.0, "y": 150.0, "z": -80.0}})
    plan = _plan(G10_L20, 9, board=moved)
    said = [t for t in plan.uncertain if "G55" in t and "G10" in t]
    assert "Z -80 where the file wrote -75" in said[0]
    assert plan.machine["z"] == -81.0


def test_a_spindle_started_without_s_keeps_the_boards_speed_never_s0() -> None:
    text = "G21 G90\nG0 X0 Y0 Z5\nM3\nG1 Z-1 F200\nG1 X30 F900\n"
    plan = _plan(text, 5, board=Board(OFFSETS, speed=18000.0))
    assert "M3" in plan.approach and not any(t.startswith("S") for t in plan.approach)
    assert any("never set a speed" in t and "S18000" in t for t in plan.uncertain)
    dwell = plan.approach.index("G4 P1")
    assert plan.approach[dwell - 1] == "M3" and "G1 Z" in plan.approach[dwell + 1]
    with pytest.raises(ResumeError, match="without a speed"):
        _plan(text, 5, board=Board(OFFSETS, speed=0.0))


def test_the_plunge_is_at_the_files_plunge_feed_or_the_configured_one_whichever_is_slower() -> None:
    text = "G21 G90\nG0 X0 Y0 Z5\nS10000 M3\nG1 Z-2 F300\nG1 X40 F1500\nG1 Y40\n"
    plan = _plan(text, 6)
    assert plan.plunge_feed == 300
    down = next(t for t in plan.approach if "G1 Z" in t)
    assert down.endswith("F300")
    # The file's cutting feed is back for the line that follows.
    assert plan.approach[plan.approach.index(down) + 1] == "F1500"
    assert _plan(text, 6, plunge_feed=120.0).plunge_feed == 120
    assert _plan(text, 6, plunge_feed=1000.0).plunge_feed == 300
    # No Z-only feed move and none configured: the cutting feed, and said.
    flat = "G21 G90\nG0 X0 Y0 Z5\nS10000 M3\nG1 X10 Y0 Z-1 F800\nG1 X40\n"
    plan = _plan(flat, 5)
    assert plan.plunge_feed == 800 and any("cutting feed" in t for t in plan.uncertain)


def test_an_inch_file_plunges_in_inches_at_its_own_feed() -> None:
    text = "G20 G90\nG0 X1 Y1 Z0.2\nS10000 M3\nG1 Z-0.05 F10\nG1 X3 F40\nG1 Y2\n"
    plan = _plan(text, 6)
    assert plan.plunge_feed == pytest.approx(254.0)
    assert next(t for t in plan.approach if "G1 Z" in t).endswith("F10")
    ran = _after(plan.lines, BOARD)
    assert _machine(ran) == _machine(_file_at(text, 6, BOARD))


def test_a_laser_moves_with_the_beam_off_and_turns_it_on_in_position() -> None:
    text = "G21 G90\nG0 X5 Y5 Z0\nM4 S800\nG1 X20 F3000\nG1 Y20\n"
    plan = _plan(text, 5, GRBL, laser=True)
    on = plan.approach.index("S800 M4")
    moves = [i for i, t in enumerate(plan.approach) if "G0" in t or "G1" in t]
    assert on > max(moves) and not any(t.startswith("G4") for t in plan.approach)
    assert "M4" not in " ".join(plan.preamble)


def test_g92_games_are_undone_and_set_again_at_the_resume_point() -> None:
    text = (
        "G21 G90 G54\nG0 X10 Y10 Z5\nG92 X0 Y0\nS9000 M3\nG1 Z-1 F250\nG1 X20 F1000\n"
        "G92.1\nG0 Z5\nG0 X0 Y0\nG92 X0 Y0 Z5\nG1 Z-2 F250\nG1 X15\n"
    )
    for line, board in ((7, BOARD), (12, BOARD), (12, Board(OFFSETS, {"x": 3.0}))):
        plan = _plan(text, line, board=board)
        ran = _after(plan.lines, board)
        want = _file_at(text, line, BOARD)
        assert _machine(ran) == _machine(want), line
        assert [round(v, 4) for v in ran.g92] == [round(v, 4) for v in want.g92], line


def test_a_g43_1_tool_length_offset_is_restored_with_its_value() -> None:
    text = "G21 G90\nG43.1 Z-12.5\nG0 X0 Y0 Z5\nS9000 M3\nG1 Z-1 F200\nG53 G0 Z-3\nG0 X9\n"
    plan = _plan(text, 7, GRBL)
    assert "G43.1 Z-12.5" in plan.preamble
    assert plan.machine["z"] == -3.0  # the retract: machine Z, whatever the offset
    down = next(t for t in plan.approach if "G1 Z" in t)
    assert down.startswith("G53 G1 Z-3 ")


def test_without_the_boards_offsets_there_is_no_plan() -> None:
    with pytest.raises(ResumeError, match="offsets are not known"):
        _plan(G53_RETRACT, 8, board=None)


# -- what the sessions read of the board -------------------------------------------


def test_grbl_reads_its_offsets_from_dollar_hash_and_its_speed_from_dollar_g() -> None:
    session = GrblSession("m1", clock=lambda: 0.0)
    assert session.offset_reads() == ["$#", "$G"]
    hash_lines = [
        "[G54:-40.000,-40.000,-20.000]",
        "[G55:-80.000,-40.000,-20.000]",
        "[G28:0.000,0.000,0.000]",
        "[G92:1.500,0.000,0.000]",
        "[TLO:0.000]",
        "[PRB:0.000,0.000,0.000:0]",
    ]
    modes = ["[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S12000]"]
    board = session.board_offsets([{"lines": hash_lines}, {"lines": modes}])
    assert board.offsets["G55"] == {"x": -80.0, "y": -40.0, "z": -20.0}
    assert "G28" not in board.offsets and board.g92["x"] == 1.5 and board.speed == 12000
    session.settings["13"] = "1"  # $13=1: $# reports inches
    inches = session.board_offsets([{"lines": ["[G54:1.000,2.000,-0.500]"]}])
    assert inches.offsets["G54"] == {"x": 25.4, "y": 50.8, "z": -12.7}
    assert inches.speed is None  # no $G answer: the board's speed is not known


def test_g2core_reads_its_offset_groups_in_the_units_in_force() -> None:
    session = G2Session("m1", clock=lambda: 0.0)
    assert session.offset_reads()[0] == '{"g54": null}' and '{"g92": null}' in (
        session.offset_reads()
    )
    bodies = [{"g54": {"x": 1, "y": 2, "z": -0.5, "a": 0}}, {"g92": {"x": 0, "y": 0, "z": 0}}]
    session.model.units = "in"  # the status report's unit: F_CONVERT values are in inches
    board = session.board_offsets(bodies)
    assert board.offsets == {"G54": {"x": 25.4, "y": 50.8, "z": -12.7}}
    assert board.g92 == {"x": 0.0, "y": 0.0, "z": 0.0} and board.speed is None
    # After M2/M30 g2core keeps the G92 values but suspends them (g92e 0): not in force.
    held = [{"g92": {"x": 5, "y": 0, "z": 0}}, {"g92e": 1}]
    assert session.board_offsets(held).g92["x"] == 5 * 25.4
    suspended = [{"g92": {"x": 5, "y": 0, "z": 0}}, {"g92e": 0}]
    assert session.board_offsets(suspended).g92 == {}


def test_a_g92_the_board_holds_is_the_files_start_only_when_the_file_sets_none() -> None:
    own = "G21 G90\nG0 X10 Y10 Z5\nG92 X0 Y0\nS9000 M3\nG1 Z-1 F200\nG1 X20 F900\nG1 Y5\n"
    # The board kept the lost job's own G92 (10, 10 from G54): reading the file from it
    # would have put the first move 10 mm off, and the file's G92 with it.
    lost = Board(OFFSETS, {"x": 10.0, "y": 10.0})
    plan = _plan(own, 7, board=lost)
    assert plan.machine == _plan(own, 7).machine == {"x": 130.0, "y": 110.0, "z": -81.0}
    assert any("replaced by the file's (line 3)" in t for t in plan.uncertain)
    # A file that sets none ran in the G92 the operator set before the job: kept.
    plain = "G21 G90\nG0 X0 Y0 Z5\nS9000 M3\nG1 Z-1 F200\nG1 X20 F900\nG1 Y5\n"
    operator = Board(OFFSETS, {"x": 3.0})
    plan = _plan(plain, 6, board=operator)
    assert plan.machine["x"] == 123.0 and "G92.1" not in plan.approach
    assert any("does not set before this line" in t for t in plan.uncertain)


def test_the_preamble_leaves_out_what_the_dialect_refuses_with_its_words() -> None:
    text = "G21 G90 G64\nG43 H2\nG0 X0 Y0 Z5\nG1 X5 F500\nG1 Y5\n"
    plan = _plan(text, 5, GRBL)
    assert plan.preamble[:2] == ["G21", "G17 G90 G91.1 G94"] and "H2" not in plan.preamble
    assert "G43 H2" in _plan(text, 5, G2CORE).preamble


CLEARANCE = """\
G21 G90 G54
G0 Z10
G0 X10 Y10
G1 Z-1 F300
G1 X60 F1500
G1 Y40
"""


@pytest.mark.parametrize(("safe_z", "climb"), [(-75.0, "-70"), (-2.0, "-2")])
def test_the_approach_never_crosses_lower_than_the_file_went_before_the_line(
    safe_z: float, climb: str
) -> None:
    """The file rose to work Z10 (machine -70) before cutting at Z-1. With a safe height
    below that (-75: set too low, say 5 mm over the stock on a 10 mm clamp) the approach
    crosses at the file's own clearance, and says so; above it, at the safe height."""
    plan = _plan(CLEARANCE, 6, safe_z=safe_z)
    assert plan.approach[0] == f"G90 G53 G0 Z{climb}"
    assert plan.approach[1] == "G53 G0 X160 Y110"  # across only once up there
    noted = [u for u in plan.uncertain if "above the safe height" in u]
    if safe_z < -70:
        assert noted == [
            "the file went up to Z-70 mm (machine, line 2), above the safe height Z-75: "
            "the approach crosses at that height"
        ]
    else:
        assert noted == []
