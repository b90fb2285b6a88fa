"""The simulator's pure pieces on their own: the input scanner, relaxed JSON, G-code."""

from __future__ import annotations

import math

import pytest

from hostd.protocol.status import Status
from hostd.sim import relaxed
from hostd.sim.gcode import Dwell, Home, Interpreter, Move, ProgramEnd
from hostd.sim.motion import path_length, point_on
from hostd.sim.scanner import ControlLine, DataLine, LineScanner, NulFlush, Realtime, ScanEvent


def scan(data: bytes, hold: bool = False) -> list[ScanEvent]:
    return list(LineScanner(lambda: hold).feed(data))


def no_limits(_: object) -> Status:
    return Status.OK


class TestScanner:
    def test_terminator_runs_collapse_and_empty_lines_vanish(self) -> None:
        assert scan(b"\r\n\nG0 X1\r\n\r\nG0 X2\n") == [DataLine(b"G0 X1"), DataLine(b"G0 X2")]

    def test_single_characters_at_line_start_are_controls(self) -> None:
        assert scan(b"!\n~\x04\x18\x05") == [Realtime(c) for c in b"!~\x04\x18\x05"]

    def test_a_bang_inside_a_line_is_data(self) -> None:
        assert scan(b"G0 X1 !\n") == [DataLine(b"G0 X1 !")]

    def test_percent_is_a_control_only_in_a_hold(self) -> None:
        assert scan(b"%\n") == [DataLine(b"%")]
        assert scan(b"%\n", hold=True) == [Realtime(ord("%"))]

    def test_percent_right_after_a_bang_is_a_control_even_at_rest(self) -> None:
        """xio.cpp:754 `_last_control_was_feedhold`: `!%` and `!\\n%\\n` flush anywhere."""
        assert scan(b"!\n%\n") == [Realtime(ord("!")), Realtime(ord("%"))]
        assert scan(b"!%") == [Realtime(ord("!")), Realtime(ord("%"))]
        assert scan(b"!\nG0\n%\n") == [Realtime(ord("!")), DataLine(b"G0"), DataLine(b"%")]

    def test_a_control_line_counts_the_terminators_already_received(self) -> None:
        assert scan(b'{"gc":"G1 X0"}\n') == [ControlLine(b'{"gc":"G1 X0"}', 15)]
        assert scan(b"{a:n}\r\n\n") == [ControlLine(b"{a:n}", 8)]

    def test_a_nul_discards_everything(self) -> None:
        scanner = LineScanner(lambda: False)
        assert list(scanner.feed(b"G0 X1\nG0 X2\x00G0 X3\n")) == [DataLine(b"G0 X1"), NulFlush()]
        assert scanner.partial == 0

    def test_a_partial_line_waits_for_its_terminator(self) -> None:
        scanner = LineScanner(lambda: False)
        assert list(scanner.feed(b"G0 X")) == []
        assert scanner.partial == 4
        assert list(scanner.feed(b"1\n")) == [DataLine(b"G0 X1")]

    def test_an_overlong_line_is_cut_and_its_tail_skipped(self) -> None:
        scanner = LineScanner(lambda: False)
        events = list(scanner.feed(b"x" * 600))
        events += list(scanner.feed(b"y" * 100 + b"\nG0\n"))
        assert events == [DataLine(b"x" * 511), DataLine(b"G0")]


class TestRelaxedJson:
    def test_unquoted_keys_and_short_literals(self) -> None:
        assert relaxed.parse("{xvm:n, sl:t, lim:f}") == {"xvm": None, "sl": True, "lim": False}

    def test_the_line_is_lower_cased_except_in_comments(self) -> None:
        assert relaxed.parse('{"GC":"G1 X1 (Hi There)"}') == {"gc": "g1x1(Hi There)"}

    def test_empty_string_is_a_get_and_objects_nest(self) -> None:
        assert relaxed.parse('{"sr":""}') == {"sr": None}
        assert relaxed.parse("{sr:{posx:t,stat:t}}") == {"sr": {"posx": True, "stat": True}}

    def test_numbers(self) -> None:
        assert relaxed.parse("{xvm:-1.5e3}") == {"xvm": -1500.0}

    @pytest.mark.parametrize("text", ["{xvm:", "xvm:n}", "{xvm:+5}", "{:1}", "{a:[1]}", "{a:1x}"])
    def test_syntax_errors(self, text: str) -> None:
        with pytest.raises(relaxed.RelaxedJsonError):
            relaxed.parse(text)


class TestGcode:
    def test_moves_in_units_and_distance_modes(self) -> None:
        g = Interpreter()
        out = g.execute("G20 G91 G1 X1 F10", no_limits)
        assert out.status == Status.OK
        (move,) = out.blocks
        assert isinstance(move, Move)
        assert move.target["x"] == pytest.approx(25.4)
        assert move.feed == pytest.approx(254.0)

    def test_feed_is_required_for_feed_moves(self) -> None:
        assert Interpreter().execute("G1 X1", no_limits).status == Status.FEEDRATE_NOT_SPECIFIED

    def test_unsupported_codes(self) -> None:
        g = Interpreter()
        assert g.execute("G33 Z-1", no_limits).status == Status.GCODE_COMMAND_UNSUPPORTED
        assert g.execute("M100", no_limits).status == Status.MCODE_COMMAND_UNSUPPORTED

    def test_a_refused_line_changes_nothing(self) -> None:
        g = Interpreter()
        g.execute("G1 X5 F100", no_limits)
        assert g.execute("G20 G1 X1 M100", no_limits).status != Status.OK
        assert g.metric
        assert g.position["x"] == 5

    def test_line_number_dwell_home_and_program_end(self) -> None:
        out = Interpreter().execute("N12 G4 P0.5 G28.2 X0 M30", no_limits)
        assert out.n == 12
        assert [type(b) for b in out.blocks] == [Dwell, Home, ProgramEnd]

    def test_t_selects_and_m6_makes_it_the_reported_tool(self) -> None:
        """canonical_machine.cpp:1392-1408: T writes tool_select, M6 sets tool from it."""
        g = Interpreter()
        assert g.execute("T3", no_limits).status == Status.OK
        assert (g.tool_select, g.tool) == (3, 0)  # selected, not yet changed
        assert g.execute("M6", no_limits).status == Status.OK
        assert g.tool == 3
        assert g.execute("T5 M6 (both in one block)", no_limits).status == Status.OK
        assert g.tool == 5
        assert g.execute("T33 M6", no_limits).status == Status.T_WORD_IS_INVALID  # > TOOLS
        assert g.tool == 5

    def test_comments_and_percent_are_ignored(self) -> None:
        g = Interpreter()
        assert g.execute("(just a comment)", no_limits).blocks == ()
        assert g.execute("G0 X1 ; to the side", no_limits).blocks[0] == Move(
            {"x": 1.0, "y": 0.0, "z": 0.0}, 0.0, 0, rapid=True
        )

    def test_soft_limits_come_from_the_check(self) -> None:
        g = Interpreter()
        out = g.execute("G0 X-1", lambda t: Status.SOFT_LIMIT_EXCEEDED_XMIN)
        assert out.status == Status.SOFT_LIMIT_EXCEEDED_XMIN
        assert g.position["x"] == 0

    def test_a_quarter_arc(self) -> None:
        g = Interpreter()
        g.execute("G0 X10", no_limits)
        (arc,) = g.execute("G3 X0 Y10 I-10 F100", no_limits).blocks
        assert isinstance(arc, Move)
        start = {"x": 10.0, "y": 0.0, "z": 0.0}
        assert path_length(start, arc) == pytest.approx(10 * math.pi / 2)
        half = point_on(start, arc, 0.5)
        assert math.hypot(half["x"], half["y"]) == pytest.approx(10)
