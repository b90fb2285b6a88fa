"""The command class table of behaviour.md, row by row, in every state."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from hostd.protocol.classes import (
    ADMISSION,
    CLEARS,
    CommandClass,
    admit,
    classify,
    classify_realtime,
)
from hostd.protocol.commands import InvalidCommand, Realtime, Refusal, validate_line
from hostd.protocol.relaxed import board_pairs, is_get, read_relaxed
from hostd.protocol.states import MachineState as S
from tests.fuzz.strategies import fuzz

Q, C, E, R, H, A = (
    CommandClass.QUERY,
    CommandClass.CLEAR,
    CommandClass.PROGRAM_END,
    CommandClass.RESET,
    CommandClass.HALT,
    CommandClass.ACTION,
)


@pytest.mark.parametrize(
    ("line", "cls"),
    [
        ('{"sr":n}', Q),
        ("{sr:n}", Q),
        ('{"xvm":null}', Q),
        ("{xvm:n}", Q),
        ('{"posx":""}', Q),
        ("$xvm", Q),
        ("?", Q),
        ("{alarm:n}", Q),
        ('{"clear":n}', C),
        ("{clear:n}", C),
        ("{clr:n}", C),
        ('{"clr":null}', C),
        ("$clear", C),
        ("$CLR", C),
        ("M2", E),
        ("M30", E),
        ("m30", E),
        (" M30 ", E),
        ("N10 M30", A),  # an N word defeats the board's match
        ("M30 X1", A),
        ("M3", A),
        ("G1 X10", A),
        ("G28.2 X0", A),
        ('{"xvm":16000}', A),
        ("$xvm=16000", A),
        ("{clear:1}", A),  # SET form: the board rejects it in alarm
        ("$clear=1", A),
        ('{"gc":"G0 X1"}', A),
        ('{"gc2":"G0 X1"}', A),
        ("{sr:{posx:t}}", A),
        ("{not json", A),
    ],
)
def test_classification(line: str, cls: CommandClass) -> None:
    assert classify(line) is cls


@pytest.mark.parametrize(
    ("command", "cls"),
    [
        (Realtime.FEEDHOLD, H),
        (Realtime.QUEUE_FLUSH, H),
        (Realtime.JOB_KILL, H),
        (Realtime.CYCLE_START, A),
        (Realtime.RESET, R),
        (Realtime.ENQUIRY, Q),
    ],
)
def test_realtime_classification(command: Realtime, cls: CommandClass) -> None:
    assert classify_realtime(command) is cls


# behaviour.md, "Command classes": (ALARM, SHUTDOWN, PANIC); None = forwarded.
TABLE = {
    Q: (None, None, None),
    C: (None, None, 206),
    E: (None, 205, 206),
    R: (None, None, None),
    H: (None, None, None),
    A: (204, 205, 206),
}


@pytest.mark.parametrize("cls", list(CommandClass))
@pytest.mark.parametrize("state", list(S))
def test_every_class_in_every_state(cls: CommandClass, state: S) -> None:
    column = {S.ALARM: 0, S.SHUTDOWN: 1, S.PANIC: 2}.get(state)
    expected = None if column is None else TABLE[cls][column]
    assert admit(cls, state) == expected


def test_unknown_state_forwards_like_before_the_first_report() -> None:
    assert admit(A, None) is None


def test_table_covers_every_class() -> None:
    assert set(ADMISSION) == set(CommandClass)


def test_what_clears_what() -> None:
    assert CLEARS[C] == {S.ALARM, S.SHUTDOWN}
    assert CLEARS[E] == {S.ALARM}
    assert CLEARS[R] == {S.ALARM, S.SHUTDOWN, S.PANIC}
    # Whatever clears a state must be admitted in it.
    for cls, states in CLEARS.items():
        for state in states:
            assert admit(cls, state) is None


def test_lockout_states() -> None:
    assert {s for s in S if s.is_lockout} == {S.ALARM, S.SHUTDOWN, S.PANIC}
    assert {s for s in S if s.is_resting} == {S.READY, S.PROGRAM_STOP, S.PROGRAM_END}


# -- a line is classified only if it is read with certainty ----------------------

json_keys = st.sampled_from(["gc", "GC", "clear", "clr", "xvm", "x", "vm", "sys", "alarm"])
json_values = st.sampled_from(["n", "null", '""', "1", '"G0 X100"', "t", "{vm:n}", "{clear:n}"])
json_lines = st.lists(
    st.tuples(json_keys, json_values).map(lambda kv: f"{kv[0]}:{kv[1]}"), min_size=1, max_size=4
).map(lambda pairs: "{" + ",".join(pairs) + "}")


@fuzz(800)
@given(json_lines)
def test_a_json_line_that_passes_is_classified_by_every_pair_it_runs(line: str) -> None:
    try:
        validate_line(line)
    except InvalidCommand:
        return
    pairs = board_pairs(read_relaxed(line))
    names = [name for names, _ in pairs for name in names]
    assert len(names) == len(set(names)), "a name the board runs twice passed"
    if classify(line) in (Q, C):
        assert all(is_get(value) for _, value in pairs), "a SET passed as a query or a clear"


def test_the_issues_line_is_refused_not_classified_as_a_clear() -> None:
    line = '{"gc":"G0 X100","clear":n,"gc":n}'
    with pytest.raises(InvalidCommand) as err:
        validate_line(line)
    assert err.value.refusal is Refusal.DUPLICATE_KEY
