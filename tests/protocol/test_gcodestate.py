"""The modal model's own rules: where g2core and grbl differ from LinuxCNC, the preamble,
what it does not know. Each dialect row is checked against the controller's source
(docs/gcode.md); LinuxCNC's side against rs274 where it can be."""

from __future__ import annotations

from pathlib import Path

import pytest

from hostd.protocol.gcodestate import G2CORE, GRBL, LINUXCNC, Dialect, GcodeModel, analyze
from hostd.protocol.gcodestate.state import AXES, WCS
from tests.protocol import rs274

ZERO = dict.fromkeys(AXES, 0.0)
KNOWN = {"start": ZERO, "offsets": {w: ZERO for w in WCS}, "homes": {"G28": ZERO, "G30": ZERO}}


def run(dialect: Dialect, text: str, **kwargs: object) -> GcodeModel:
    options = {**KNOWN, **kwargs}
    return GcodeModel(dialect, **options).feed_lines(text.splitlines())  # type: ignore[arg-type]


def canon(tmp_path: Path, text: str) -> list[tuple[str, str]]:
    path = tmp_path / "t.ngc"
    path.write_text(text)
    return rs274.run(path, set(), tmp_path).canon


PROGRAM_END = "G21 G91 G19 G55 F100 S500 M3 M8\nG1 X1\nG92 X0\nG1 X1\nM2\n"


def test_m2_on_linuxcnc_keeps_g92_and_zeroes_the_feed(tmp_path: Path) -> None:
    state = run(LINUXCNC, PROGRAM_END).state()
    assert (state.wcs, state.plane, state.distance, state.motion) == ("G54", "G17", "G90", "G1")
    assert (state.spindle, state.flood, state.feed, state.speed) == ("M5", False, 0.0, 500)
    assert state.g92["x"] == 1.0
    after = canon(tmp_path, PROGRAM_END)
    end = after[[name for name, _ in after].index("PROGRAM_END") - 8 :]
    assert ("SET_FEED_RATE", "0.0000") in end
    assert not any(name == "SET_G92_OFFSET" for name, _ in end)


def test_m2_on_g2core_suspends_g92_and_cancels_the_motion_mode() -> None:
    state = run(G2CORE, PROGRAM_END).state()
    assert (state.wcs, state.plane, state.distance, state.motion) == ("G54", "G17", "G90", "G80")
    assert state.g92["x"] == 0.0 and state.g92_stored["x"] == 1.0
    assert state.feed == 100  # kept


def test_m2_on_grbl_keeps_g92_and_the_feed() -> None:
    state = run(GRBL, PROGRAM_END).state()
    assert (state.motion, state.g92["x"], state.feed) == ("G1", 1.0, 100)


HOME = "G0 X10 Y20 Z30\nG28 X5\n"


def test_g28_with_an_axis_word_homes_only_that_axis_on_linuxcnc() -> None:
    assert run(LINUXCNC, HOME).state().machine == {**ZERO, "y": 20.0, "z": 30.0}


@pytest.mark.parametrize("dialect", [G2CORE, GRBL])
def test_g28_with_an_axis_word_homes_every_axis_on_g2core_and_grbl(dialect: Dialect) -> None:
    assert run(dialect, HOME).state().machine == ZERO


def test_g28_without_a_known_home_leaves_the_position_unknown_until_an_absolute_move() -> None:
    model = run(G2CORE, HOME, homes=None)
    assert model.state().machine["x"] is None
    assert any("G28" in w for w in model.warnings)
    model.step("G0 X1 Y2 Z3")
    work = model.state().work
    assert (work["x"], work["y"], work["z"], work["a"]) == (1.0, 2.0, 3.0, None)


L20 = "G0 X10\nG92 X0\nG10 L20 P1 X5\n"


@pytest.mark.parametrize(("dialect", "offset"), [(LINUXCNC, -5.0), (GRBL, -5.0), (G2CORE, 5.0)])
def test_g10_l20_counts_g92_except_on_g2core(dialect: Dialect, offset: float) -> None:
    # machine X10, G92 offset 10: LinuxCNC and grbl put work X at 5; g2core ignores G92.
    assert run(dialect, L20).state().wcs_offsets["G54"]["x"] == offset


def test_f_keeps_its_number_across_g20_on_linuxcnc_and_its_speed_on_g2core() -> None:
    assert run(LINUXCNC, "G21 F100\nG20\n").state().feed == 100
    assert run(G2CORE, "G21 F100\nG20\n").state().feed == pytest.approx(100 / 25.4)
    assert run(GRBL, "G21 F100\nG20\n").state().feed == pytest.approx(100 / 25.4)


def test_g2core_reads_f_before_the_g20_of_the_same_block() -> None:
    assert run(G2CORE, "G21\nG20 F10\n").state().feed == pytest.approx(10 / 25.4)
    assert run(GRBL, "G21\nG20 F10\n").state().feed == 10
    assert run(LINUXCNC, "G21\nG20 F10\n").state().feed == 10


def _arc_off_by(error: float) -> str:
    return f"G21 G0 X0 Y0\nG2 X20 Y0 I10 J0 F100\nG2 X{-error} Y0 I-10 J0\nM2\n"


@pytest.mark.parametrize(("error", "refused"), [(0.028, False), (0.0285, True), (0.02, False)])
def test_an_arc_that_does_not_close_is_flagged_where_rs274_refuses_it(
    tmp_path: Path, error: float, refused: bool
) -> None:
    text = _arc_off_by(error)
    path = tmp_path / "arc.ngc"
    path.write_text(text)
    result = rs274.run(path, set(), tmp_path)
    assert any("Radius to end of arc differs" in e for e in result.errors) == refused
    warned = any("does not close" in w for w in run(LINUXCNC, text).warnings)
    assert warned == refused


@pytest.mark.parametrize("dialect", [G2CORE, GRBL])
def test_g2core_and_grbl_are_stricter_about_arcs_than_linuxcnc(dialect: Dialect) -> None:
    # 0.02 mm on a 10 mm radius: over 0.005 mm and 0.1 %, refused by both boards.
    assert any("does not close" in w for w in run(dialect, _arc_off_by(0.02)).warnings)


PROGRAM = """G20 G90 G18
G10 L2 P2 X1 Y2
G55 G91.1 G61
T4 M6
T5
F12.5 S9000 M4 M7 M8
G1 X1 Z1
"""


def test_the_preamble_puts_a_fresh_controller_into_the_same_modal_state() -> None:
    state = run(G2CORE, PROGRAM).state()
    preamble = state.preamble()
    assert preamble == [
        "G20",
        "G18 G90 G91.1 G94 G61",
        "G55",  # never G10: the board stores its offsets (issue 24)
        "T4 M6",
        "T5",
        "F12.5",
        "S9000 M4",
        "M7",
        "M8",
    ]
    fresh = run(G2CORE, "\n".join(preamble)).state()
    for field in ("units", "distance", "arc_distance", "plane", "wcs", "feed_mode", "feed"):
        assert getattr(fresh, field) == getattr(state, field), field
    for field in ("path", "spindle", "speed", "mist", "flood", "tool", "selected_tool"):
        assert getattr(fresh, field) == getattr(state, field), field


def test_a_g92_offset_is_named_as_unrestorable_and_written_for_a_known_position() -> None:
    state = run(G2CORE, "G0 X10 Y10\nG92 X0 Y0\n").state()
    assert any("G92" in text for text in state.unrestorable())
    line = state.g92_line({"x": 30.0, "y": 10.0})
    assert line == "G92 X20 Y0"
    fresh = run(G2CORE, f"G0 X30 Y10\n{line}\n").state()
    assert fresh.g92 == state.g92


def test_comments_line_numbers_block_delete_and_tape_marks() -> None:
    text = "%\nN5 G0 X1 (move) ; and more\n/G0 X9\n( only a comment )\n%\n"
    state = run(G2CORE, text).state()
    assert (state.line, state.n, state.work["x"]) == (5, 5, 9.0)
    assert run(G2CORE, text, block_delete=True).state().work["x"] == 1.0


def test_without_a_start_position_the_model_says_it_does_not_know() -> None:
    model = GcodeModel(G2CORE).feed_lines(["G91 G0 X1", "G90 G0 Y2"])
    state = model.state()
    assert state.machine["x"] is None and state.machine["y"] is None  # offsets unknown
    assert GcodeModel(G2CORE, offsets={"G54": ZERO}).feed_lines(["G0 Y2"]).state().work["y"] == 2


def test_unknown_and_unsupported_codes_are_warnings_with_their_first_line() -> None:
    result = analyze(["G21", "G0 X1", "G5.1 X2", "#1 = 2", "M123", "G95 F1", "G95 F1"], GRBL)
    texts = {w.text: (w.line, w.count) for w in result.warnings}
    assert texts["G5.1 is not supported"] == (3, 1)
    assert texts["parameters and expressions are not modelled: the line is ignored"] == (4, 1)
    assert texts["M123 is not supported"] == (5, 1)
    assert texts["G95 is not supported by grbl"] == (6, 2)


def test_analysis_figures_of_an_inch_program() -> None:
    text = "G20 T1 M6 S18000 M3\nG0 X1 Y1\nG1 Z-0.5 F10\nG2 X3 Y1 I1 J0\nT2 M6\nM2\n"
    result = analyze(text.splitlines(), G2CORE)
    assert (result.lines, result.rapids, result.feeds, result.arcs) == (6, 1, 2, 1)
    assert result.file_units == "G20" and result.tools == (1, 2) and result.max_speed == 18000
    # Where the moves go (not the start): the arc's top is at Y2.
    assert result.bounds_in("G20")["y"] == pytest.approx((1.0, 2.0))
    assert result.bounds["x"] == pytest.approx((25.4, 3 * 25.4))
