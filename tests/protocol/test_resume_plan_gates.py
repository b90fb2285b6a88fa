"""The resume plan's rules that a mutation campaign over resume.py and the model found
untested: each mutant that survived the existing tests and changed what a machinist
would see has a test here.

Each test asserts the lines the plan sends, in order, with their values, or the
refusal. The rules: docs/operations.md, "How the approach is planned" and its limits;
hostd/protocol/gcodestate/resume.py. The machine: G54 at 100, 100, -80 from machine
zero (tests/protocol/test_resume_plan.py), a safe height of machine Z-2, a 1 s dwell.
"""

from __future__ import annotations

import pytest

from hostd.protocol.gcodestate import G2CORE, GRBL, LINUXCNC, Dialect
from hostd.protocol.gcodestate.resume import Board, ResumeError
from tests.protocol.test_resume_plan import BOARD, OFFSETS, ZERO, _plan

MILL = "G21 G90\nG0 X0 Y0 Z5\nS9000 M3\nG1 Z-1 F200\nG1 X20 F900\nG1 Y5\n"


# -- the approach: heights, order, units -----------------------------------------


def test_an_inch_file_climbs_to_the_safe_height_in_inches() -> None:
    """The safe height is machine mm, and after the preamble's G20 the board reads G53's
    Z in inches: machine Z-2 mm is `Z-0.07874`; `Z-2` would be 50.8 mm down."""
    text = "G20 G90\nG0 X1 Y1 Z0.2\nS10000 M3\nG1 Z-0.05 F10\nG1 X3 F40\nG1 Y2\n"
    plan = _plan(text, 6)
    assert plan.preamble[0] == "G20"
    assert plan.approach == [
        "G90 G53 G0 Z-0.07874",
        "G53 G0 X6.937008 Y4.937008",
        "S10000 M3",
        "G4 P1",
        "G53 G1 Z-3.199606 F10",
        "F40",
    ]


def test_the_files_clearance_counts_with_its_g43_1_tool_length_offset() -> None:
    """A bug the campaign found: the file's highest Z was taken without its G43.1 offset.
    With `G43.1 Z10` the file's `G0 Z10` put the machine at Z-60; the approach crossed
    at Z-70, 10 mm lower than the file did (the tool's tip at the stock's top), and
    said the file went up to Z-70. A negative offset keeps the safe height (-75): the
    file's clearance was then machine -80."""
    text = (
        "G21 G90 G54\nG43.1 Z{tlo}\nG0 Z10\nG0 X10 Y10\nS9000 M3\nG1 Z-1 F300\n"
        "G1 X60 F1500\nG1 Y40\n"
    )
    longer = _plan(text.format(tlo=10), 8, GRBL, safe_z=-75.0)
    assert longer.approach[:2] == ["G90 G53 G0 Z-60", "G53 G0 X160 Y110"]
    assert longer.approach[-2:] == ["G53 G1 Z-71 F300", "F1500"]
    assert any("the file went up to Z-60 mm (machine, line 3)" in t for t in longer.uncertain)
    shorter = _plan(text.format(tlo=-10), 8, GRBL, safe_z=-75.0)
    assert shorter.approach[:2] == ["G90 G53 G0 Z-75", "G53 G0 X160 Y110"]
    assert shorter.approach[-2:] == ["G53 G1 Z-91 F300", "F1500"]
    assert not any("the file went up" in t for t in shorter.uncertain)


def test_a_g43_1_offset_in_an_inch_file_is_restored_in_inches() -> None:
    """`G43.1 Z-0.5` in a G20 file is 12.7 mm; written back as `Z-12.7` after the
    preamble's G20 it would be 12.7 inches."""
    text = "G20 G90\nG43.1 Z-0.5\nG0 X0 Y0 Z0.2\nS9000 M3\nG1 Z-0.05 F10\nG1 X1 F40\n"
    plan = _plan(text, 6, GRBL)
    assert plan.preamble == ["G20", "G17 G90 G91.1 G94", "G54", "G43.1 Z-0.5", "F10", "S9000"]
    assert plan.approach[-2:] == ["G53 G1 Z-3.699606 F10", "F10"]


@pytest.mark.parametrize(
    ("text", "down"),
    [
        (
            "G21 G90 G54\nG43 H1\nG0 X10 Y10 Z5\nS9000 M3\nG1 Z-1 F200\nG1 X30 F900\n",
            ["G53 G0 X110 Y110", "G1 Z-1 F200"],
        ),
        (
            "G20 G90 G54\nG43 H1\nG0 X0.5 Y0.5 Z0.2\nS9000 M3\nG1 Z-0.04 F8\nG1 X1 F30\n",
            ["G53 G0 X4.437008 Y4.437008", "G1 Z-0.04 F8"],
        ),
    ],
    ids=["mm", "inch"],
)
def test_under_g43_the_tool_goes_down_to_the_files_own_depth(text: str, down: list[str]) -> None:
    """G43 H: the offset is in the board's tool table, so the plunge is in the file's
    coordinates (`G1 Z-1`), where the board adds it; `Z-81` would be machine Z in work
    coordinates, 80 mm into the stock (operations.md, step 6)."""
    plan = _plan(text, 6)
    climb = "G90 G53 G0 Z-0.07874" if text.startswith("G20") else "G90 G53 G0 Z-2"
    assert plan.approach == [climb, down[0], "S9000 M3", "G4 P1", down[1], down[1].split()[-1]]
    assert plan.machine["z"] is None  # the machine's Z needs the table's value


def test_under_g43_the_plan_says_the_files_clearance_is_not_known() -> None:
    """G43 H moves the file's heights by the tool table's offset, which hostd cannot read:
    a positive one lifts the file's clearance above what its lines say, and the approach,
    at the safe height or the programmed clearance, may cross below it. The plan says so,
    with the height it crosses at, for the operator to check."""
    text = "G21 G90 G54\nG43 H1\nG0 X10 Y10 Z5\nS9000 M3\nG1 Z-1 F200\nG1 X30 F900\n"
    plan = _plan(text, 6)
    (said,) = [t for t in plan.uncertain if "clearance" in t]
    assert said.startswith("the file ran under G43 from line 3: its heights moved by")
    assert "the approach crosses at Z-2 mm (machine)" in said
    plain = _plan(text.replace("G43 H1\n", "G49\n"), 6)
    assert not any("clearance" in t for t in plain.uncertain)


def test_under_g43_a_g92_the_board_holds_counts_in_the_plunge() -> None:
    """An operator's G92 Z2, held by the board and not set by the file: not cleared, so
    the plunge in the file's coordinates goes to the file's Z-1, not 2 mm off it."""
    text = "G21 G90 G54\nG43 H1\nG0 X10 Y10 Z5\nS9000 M3\nG1 Z-1 F200\nG1 X30 F900\n"
    plan = _plan(text, 6, board=Board(OFFSETS, {"x": 0.0, "y": 0.0, "z": 2.0}))
    assert plan.approach == [
        "G90 G53 G0 Z-2",
        "G53 G0 X110 Y110",
        "S9000 M3",
        "G4 P1",
        "G1 Z-1 F200",
        "F200",
    ]


def test_the_approach_goes_to_the_files_point_to_a_tenth_of_a_micron() -> None:
    """mm to 4 places: a resume point rounded to 0.1 mm would start the line with a
    step in the cut."""
    text = "G21 G90\nG0 X12.3456 Y7.0625 Z5\nS9000 M3\nG1 Z-1.25 F200\nG1 X20 F900\n"
    plan = _plan(text, 5)
    assert plan.approach[1] == "G53 G0 X112.3456 Y107.0625"
    assert plan.approach[-2:] == ["G53 G1 Z-81.25 F200", "F200"]


def test_an_operators_g92_the_board_reads_on_every_axis_is_kept() -> None:
    """g2core reports G92 for every axis, zeros included: an offset on X alone is still
    the operator's, set before the job (the file sets none), and the job ran in it."""
    plan = _plan(MILL, 6, board=Board(OFFSETS, {"x": 3.0, "y": 0.0, "z": 0.0}))
    assert plan.approach == [
        "G90 G53 G0 Z-2",
        "G53 G0 X123 Y100",
        "S9000 M3",
        "G4 P1",
        "G53 G1 Z-81 F200",
        "F900",
    ]


# -- spindle, coolant, feed and the modes put back -------------------------------------


@pytest.mark.parametrize("coolant", [["M7", "M8"], ["M7"], ["M8"]], ids=" ".join)
def test_coolant_stays_off_while_the_tool_travels_and_comes_on_before_the_spindle(
    coolant: list[str],
) -> None:
    """Mist (M7) and flood (M8), each as the file had it, on only once across."""
    text = f"G21 G90 G54\nG0 X10 Y10 Z5\n{' '.join(coolant)}\nS12000 M3\nG1 Z-1 F300\nG1 X60\n"
    plan = _plan(text, 6)
    assert plan.preamble == ["G21", "G17 G90 G91.1 G94 G64", "G54", "F300", "S12000"]
    assert plan.approach == [
        "G90 G53 G0 Z-2",
        "G53 G0 X110 Y110",
        *coolant,
        "S12000 M3",
        "G4 P1",
        "G53 G1 Z-81 F300",
        "F300",
    ]


def test_a_speed_set_while_the_spindle_is_off_is_restored_for_the_files_bare_m3() -> None:
    """Line 9 is a bare `M3`: it must run at the file's S12000, which the preamble
    sets, not at the board's speed after a reset (0 on grbl: a plunge with the
    spindle still)."""
    text = (
        "G21 G90\nG0 X0 Y0 Z5\nS12000 M3\nG1 Z-1 F200\nG1 X20 F900\nM5\nG0 Z5\nG0 X40\nM3\nG1 Z-1\n"
    )
    plan = _plan(text, 9, GRBL)
    assert plan.preamble == ["G21", "G17 G90 G91.1 G94", "G54", "F900", "S12000"]
    assert plan.approach == [
        "G90 G53 G0 Z-2",
        "G53 G0 X140 Y100",
        "G53 G1 Z-75 F200",
        "F900",
        "G0",
    ]


def test_a_laser_the_file_set_to_s0_comes_back_at_s0_not_the_boards_power() -> None:
    """A laser at S0 (a move the file makes without burning): the beam comes back at
    S0, not at the power before it (S800) nor at the board's own (S1000)."""
    text = "G21 G90\nG0 X5 Y5 Z0\nM4 S800\nG1 X20 F3000\nS0\nG0 X30\nG1 X40\n"
    plan = _plan(text, 7, GRBL, laser=True, board=Board(OFFSETS, speed=1000.0))
    assert plan.approach == [
        "G90 G53 G0 Z-2",
        "G53 G0 X130 Y105",
        "G53 G1 Z-80 F3000",
        "S0 M4",
        "F3000",
        "G0",
    ]


def test_an_inverse_time_file_plunges_in_mm_per_minute_then_gets_g93_back() -> None:
    """Under G93 an F is 1/minutes for the whole move: the plunge's F200 would take
    the 79 mm down in 0.3 s. It goes in G94, and G93 is put back for the file."""
    text = "G21 G90\nG0 X0 Y0 Z5\nS9000 M3\nG1 Z-1 F200\nG93\nG1 X10 F60\nG1 X20 F30\n"
    plan = _plan(text, 7)
    assert plan.approach == [
        "G90 G53 G0 Z-2",
        "G53 G0 X110 Y100",
        "S9000 M3",
        "G4 P1",
        "G94 G53 G1 Z-81 F200",
        "G93",
    ]
    assert "G93: inverse-time feed is given on every move, not restored" in plan.uncertain


def test_an_incremental_file_resumes_in_g91_from_the_summed_position() -> None:
    text = "G21 G90\nG0 X0 Y0 Z5\nS9000 M3\nG1 Z-1 F200\nG91\nG1 X10 F900\nG1 X10\nG1 Y5\n"
    plan = _plan(text, 8)
    assert plan.machine == {"x": 120.0, "y": 100.0, "z": -81.0}
    assert plan.approach == [
        "G90 G53 G0 Z-2",
        "G53 G0 X120 Y100",
        "S9000 M3",
        "G4 P1",
        "G53 G1 Z-81 F200",
        "F900",
        "G91",
    ]


@pytest.mark.parametrize(
    ("text", "mode"),
    [
        ("G21 G90\nG0 X0 Y0 Z5\nS9000 M3\nG1 Z-1 F200\nG1 X10 F900\nG0 X20\nY20\n", "G0"),
        ("G21 G90\nG0 X0 Y0 Z5\nS9000 M3\nG1 Z-1 F200\nG1 X10 F900\nG80\nG1 X20\n", "G80"),
    ],
    ids=["rapid", "cancelled"],
)
def test_a_rapid_or_cancelled_motion_mode_is_put_back_after_the_approach(
    text: str, mode: str
) -> None:
    """The approach ends in G1; a next line without its own G code runs in the file's
    mode: `Y20` after `G0 X20` is a rapid, not a feed move."""
    assert _plan(text, 7).approach[-2:] == ["F900", mode]


# -- the plunge's feed --------------------------------------------------------------


def test_without_a_plunge_feed_an_inch_files_cutting_feed_is_converted() -> None:
    text = "G20 G90\nG0 X1 Y1 Z0.2\nS10000 M3\nG1 X2 Y1 Z-0.05 F40\nG1 X3\n"
    plan = _plan(text, 5)
    assert plan.plunge_feed == pytest.approx(1016.0)  # 40 in/min
    assert plan.approach[-2:] == ["G53 G1 Z-3.199606 F40", "F40"]
    assert any("cutting feed (1016 mm/min)" in t for t in plan.uncertain)


def test_no_feed_to_go_down_at_is_refused() -> None:
    with pytest.raises(ResumeError, match="no feed to go down at before line 4"):
        _plan("G21 G90\nG0 X0 Y0 Z5\nS9000 M3\nG0 X10\n", 4)


# -- refused --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "line", "dialect", "axes"),
    [
        ("G21 G90\nG0 X10 Y10\nS9000 M3\nG1 X20 F900\nG1 Y20\n", 5, G2CORE, "Z"),
        ("G21 G90\nG0 X0 Y0 Z5\nG38.2 Z-10 F100\nG1 X10 F900\n", 4, G2CORE, "Z"),
        ("G21 G91\nG0 X5 Y5 Z5\nG1 X10 F900\n", 3, G2CORE, "X, Y, Z"),
        ("G21 G90\nG0 X0 Y0 Z5\nG28\nG1 X10 F900\n", 4, GRBL, "X, Y, Z"),
        ("G21 G90\nG0 X0 Y0 Z5\nG81 X10 Y10 Z-2 R1 F100\nG80\nG0 X20\n", 5, LINUXCNC, "Z"),
    ],
    ids=["z-never-set", "after-a-probe", "incremental-from-unknown", "after-g28", "after-g81"],
)
def test_no_resume_where_the_position_at_the_line_is_not_known(
    text: str, line: int, dialect: Dialect, axes: str
) -> None:
    """operations.md: if no absolute move sets X, Y and Z before the line, there is no
    resume (1011). A probe stops where it touches, a canned cycle leaves Z where its
    mode says, G28 goes to the board's stored point: none is known from the file."""
    with pytest.raises(
        ResumeError, match=rf"position at line {line} is not known from the file \({axes}:"
    ):
        _plan(text, line, dialect)


def test_a_resume_past_the_files_last_line_is_refused() -> None:
    with pytest.raises(ResumeError, match="the file has 6 lines: there is no line 8"):
        _plan(MILL, 8)


def test_without_a_safe_height_there_is_no_plan() -> None:
    with pytest.raises(ResumeError, match="no safe height: set the machine's safe_z, or home it"):
        _plan(MILL, 6, safe_z=None)


def test_a_g10_to_a_coordinate_system_the_board_does_not_hold_is_refused() -> None:
    text = "G21 G90 G54\nG10 L2 P3 X0 Y0 Z0\nG0 X0 Y0 Z5\nS9000 M3\nG1 Z-1 F200\nG1 X10 F900\n"
    with pytest.raises(ResumeError, match="sets G56 with G10 and the board has no G56"):
        _plan(text, 6, board=BOARD)  # G54 and G55 only


def test_a_g10_the_board_holds_half_a_millimetre_off_is_said_to_differ() -> None:
    text = "G21 G90\nG10 L2 P2 X150 Y150 Z-75\nG55\nG0 X0 Y0 Z5\nS9000 M3\nG1 Z-1 F200\nG1 X20\n"
    board = Board({**OFFSETS, "G55": {**ZERO, "x": 150.5, "y": 150.0, "z": -75.0}})
    plan = _plan(text, 7, board=board)
    said = [t for t in plan.uncertain if t.startswith("the file sets G55 with G10")]
    assert said and "X 150.5 where the file wrote 150; Y 150, as the file wrote" in said[0]
    assert plan.approach[1] == "G53 G0 X150.5 Y150"  # the board's G55: what the file runs in


# -- what the plan cannot restore is said ---------------------------------------------


@pytest.mark.parametrize(
    ("text", "line", "said"),
    [
        (
            "G21 G90\nG0 X0 Y0 Z5\nS9000 M3\nG1 Z-1 F200\nM30\nG0 X10\n",
            6,
            "the program ended (M2/M30) before this line",
        ),
        (
            "G21 G90\nG0 X0 Y0 Z5\nS9000 M3\nG1 Z-1 F200\nG2 X10 Y0 I5 J0 F900\nX0 Y0 I-5 J0\n",
            6,
            "the motion mode was G2: it is G1 after the approach, so a line that continues "
            "the arc without its own G2/G3 would be a straight move",
        ),
        (
            "G21 G90\nG0 X0 Y0 Z5 A90\nS9000 M3\nG1 Z-1 F200\nG1 X10 F900\n",
            5,
            "rotary axes (A) are not moved by the approach",
        ),
    ],
    ids=["ended", "arc-mode", "rotary"],
)
def test_what_the_approach_does_not_restore_is_said(text: str, line: int, said: str) -> None:
    """operations.md, `uncertain`: the program ended before the line, the arc mode,
    rotary axes."""
    assert said in _plan(text, line).uncertain
