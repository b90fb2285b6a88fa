"""The shared G-code tokenizer, and every G-code reader built on it, run in linear time.

Three ways of holding them to it:

- the line that froze the daemon (issue 24: "X111" sixteen times and a `#`, 27 s
  in the old model's regex, exponentially more per word) is read at once, here
  with 40 words: the old pattern would not finish in this test's lifetime;
- the tokenizer's patterns are checked by their structure: no repetition that
  can give a character back, no alternation whose branches can start alike;
- each reader is fed random and adversarial lines (long digit runs, many words,
  every character class) at n and 8n characters: its CPU time may grow 8x,
  with threefold slack, never the 64x of a quadratic reader.
"""

from __future__ import annotations

import contextlib
import re
import time
from collections.abc import Callable
from re import _constants as sre_constants  # type: ignore[attr-defined]
from re import _parser as sre_parse  # type: ignore[attr-defined]
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hostd.protocol import gcode, gcodewords, maintenance, textmode
from hostd.protocol.gcodestate import G2CORE, GRBL, GcodeModel, analyze
from hostd.protocol.gcodestate.model import ProgramError
from hostd.protocol.grbl import codec
from hostd.protocol.program import number_line, strip_line
from hostd.protocol.refusals import InvalidCommand
from hostd.protocol.status import Status
from hostd.sim import gcode as g2sim
from hostd.sim.grbl import parser as grblsim

HOSTILE = "X111" * 40 + "#"


def test_the_line_that_froze_the_daemon_is_read_at_once() -> None:
    a = analyze([HOSTILE, "G0 X1"], G2CORE)
    assert a.lines == 2 and a.rapids == 1
    assert [w.line for w in a.warnings] == [1]
    assert "parameters" in a.warnings[0].text


def test_read_words_splits_and_says_where_reading_stopped() -> None:
    assert gcodewords.read_words("G1 X-1.5 Y.5 F 300") == (
        [("G", "1"), ("X", "-1.5"), ("Y", ".5"), ("F", "300")],
        18,
    )
    assert gcodewords.read_words("X111X111#")[1] == 8
    assert gcodewords.read_words("X1 Y")[1] == 3  # a letter without a number
    assert gcodewords.read_words("X- 1")[1] == 0  # no space inside a number


def test_strip_comments_is_flat_and_says_when_one_is_unclosed() -> None:
    assert gcodewords.strip_comments("G1 (a (b) X1 ; c") == ("G1   X1 ", False)
    assert gcodewords.strip_comments("G1 (a ; b) X1", "") == ("G1  X1", False)
    assert gcodewords.strip_comments("G1 X1 (abc") == ("G1 X1 ", True)


def test_a_number_a_board_cannot_read_is_refused_with_its_line() -> None:
    model = GcodeModel(G2CORE)
    model.step("G1 X1 F100")
    with pytest.raises(ProgramError) as wide:
        model.step("G1 X" + "9" * 400)
    assert wide.value.line == 2 and "integer digits" in wide.value.message
    with pytest.raises(ProgramError) as nan:
        GcodeModel(GRBL).feed_lines(["G0 X1", "", "G1 F nan"])
    assert nan.value.line == 3 and "inf or nan" in nan.value.message
    # Nine digits, leading zeros and long decimals are numbers a board reads.
    GcodeModel(G2CORE).feed_lines(["G1 X999999999 F0000000000001.00000000000000001"])


# --- linear by structure ---------------------------------------------------------


def _first(items: Any) -> set[int] | None:
    """The first characters a sequence of parsed items can start with (None: unknown)."""
    for op, av in items:
        if op is sre_constants.LITERAL:
            return {av}
        if op is sre_constants.IN:
            chars: set[int] = set()
            for kind, value in av:
                if kind is sre_constants.LITERAL:
                    chars.add(value)
                elif kind is sre_constants.RANGE:
                    chars.update(range(value[0], value[1] + 1))
                else:
                    return None
            return chars
        if op is sre_constants.SUBPATTERN:
            return _first(av[-1])
        if op in (sre_constants.POSSESSIVE_REPEAT, sre_constants.MAX_REPEAT) and av[0] >= 1:
            return _first(av[2])
        return None
    return None


def _backtrack_free(items: Any) -> list[str]:
    """Where a parsed pattern could try two ways of matching the same text."""
    problems: list[str] = []
    for op, av in items:
        if op in (sre_constants.MAX_REPEAT, sre_constants.MIN_REPEAT) and av[0] != av[1]:
            problems.append(f"a repetition that gives back: {op} {av[:2]}")
        if op in (
            sre_constants.MAX_REPEAT,
            sre_constants.MIN_REPEAT,
            sre_constants.POSSESSIVE_REPEAT,
        ):
            problems += _backtrack_free(av[2])
        elif op is sre_constants.SUBPATTERN:
            problems += _backtrack_free(av[-1])
        elif op is sre_constants.ATOMIC_GROUP:
            *before, (last, last_av) = av
            if last is sre_constants.MAX_REPEAT:
                # `(?>(?:...)*)`, the possessive repeat written so every 3.11 matches it
                # right (tests/test_patterns.py): nothing in the group after it can make
                # it give an iteration back, and the group never does.
                problems += _backtrack_free(before) + _backtrack_free(last_av[2])
            else:
                problems += _backtrack_free(av)
        elif op is sre_constants.BRANCH:
            seen: set[int] = set()
            for branch in av[1]:
                first = _first(branch)
                folded = None if first is None else {ord(chr(c).lower()) for c in first}
                if folded is None or folded & seen:
                    problems.append("an alternation whose branches can start alike")
                else:
                    seen |= folded
                problems += _backtrack_free(branch)
    return problems


@pytest.mark.parametrize(
    "pattern",
    [p for p in vars(gcodewords).values() if isinstance(p, re.Pattern)],
    ids=lambda p: p.pattern[:30],
)
def test_every_tokenizer_pattern_is_deterministic(pattern: re.Pattern[str]) -> None:
    assert _backtrack_free(sre_parse.parse(pattern.pattern, pattern.flags)) == []


def test_the_structure_check_catches_the_old_pattern() -> None:
    old = r"(?:[ \t]*[A-Z][ \t]*[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+))*[ \t]*"
    assert _backtrack_free(sre_parse.parse(old)) != []
    # Inside an atomic group a greedy repeat is let off only as the group's last item,
    # and what it repeats is still checked.
    assert _backtrack_free(sre_parse.parse(r"(?>[0-9]*[0-9])")) != []
    assert _backtrack_free(sre_parse.parse(r"(?>(?:[0-9]+\.?[0-9]*)*)")) != []
    assert _backtrack_free(sre_parse.parse(r"(?>(?:[0-9]++\.?+)*)")) == []


# --- linear by measure -----------------------------------------------------------


def _model(line: str) -> None:
    with contextlib.suppress(ProgramError):
        GcodeModel(G2CORE).step(line)


def _check(line: str) -> None:
    with contextlib.suppress(InvalidCommand):
        gcode.check_gcode(line)


def _program(line: str) -> None:
    number_line(strip_line(line) or "G0", 7)


def _g2_board(line: str) -> None:
    g2sim.Interpreter().execute(line, lambda _target: Status.OK)


def _grbl_board(line: str) -> None:
    grblsim.execute(grblsim.Modal(), line, travel_ok=lambda _target: True)


def _grbl_encode(line: str) -> None:
    with contextlib.suppress(InvalidCommand):
        codec.encode(line, max_bytes=1 << 20)


def _text_command(line: str) -> None:
    with contextlib.suppress(InvalidCommand):
        textmode.read_text_command("$a=" + line)


def _grbl_maintenance(line: str) -> None:
    maintenance.grbl_maintenance(line, {}, False)  # every machine.send to a grbl board


def _powered(line: str) -> None:
    # What a sent line does that a blocking fault forbids (machine.send, .maintenance).
    maintenance.grbl_powered(line)
    maintenance.grbl_powered("$N0=" + line)
    maintenance.g2core_powered(line)
    maintenance.g2core_powered('{"gc":"' + line + '"}')


READERS: dict[str, Callable[[str], None]] = {
    "model": _model,
    "check_gcode": _check,
    "program": _program,
    "g2core sim": _g2_board,
    "grbl sim": _grbl_board,
    "grbl encode": _grbl_encode,
    "text command": _text_command,
    # Quadratic on a line of `(`s until 2026-11-29 (maintenance.normalized).
    "grbl maintenance": _grbl_maintenance,
    "powered": _powered,
}
# Every character class a line can hold, and the pieces that made the old readers slow.
_CHARS = "GXYZFNMgxy0123456789.-+ \t()(;%*#[]eE$=:|\x00\x7fé"
_PIECES = ["X111", "1", "(", " ", "X1.", "((", "#", "1 ", "e", "X", ";", ")", "9" * 20, "N1 "]
_UNIT = st.one_of(st.text(alphabet=_CHARS, min_size=1, max_size=8), st.sampled_from(_PIECES))
SIZE = 1000  # characters of the short line; the long one has 8x as many
SLACK = 3.0


def _cpu(reader: Callable[[str], None], line: str, calls: int) -> float:
    best = float("inf")
    for _ in range(3):
        start = time.process_time()
        for _ in range(calls):
            reader(line)
        best = min(best, time.process_time() - start)
    return best


@pytest.mark.parametrize("name", list(READERS))
@settings(
    max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(units=st.lists(_UNIT, min_size=1, max_size=4), tail=st.sampled_from(["", "#", "X", "("]))
def test_each_reader_costs_in_proportion_to_the_line(
    name: str, units: list[str], tail: str
) -> None:
    reader = READERS[name]
    unit = "".join(units)
    short = unit * (SIZE // len(unit) + 1) + tail
    long = unit * (8 * SIZE // len(unit) + 8) + tail
    calls = 8
    small = _cpu(reader, short, calls)
    while small < 0.003:  # long enough to measure: CPU time, not a clock's noise
        calls *= 2
        small = _cpu(reader, short, calls)
    large = _cpu(reader, long, calls)
    ratio = large / small
    assert ratio < 8 * SLACK, f"{name}: {len(long)} characters cost {ratio:.1f}x {len(short)}"
