"""g2core's session: when a line may reach the board, byte by byte on the wire.

Each test pins one gate of `G2Flow._pump`, `send` and the kill's fence
(docs/protocol.md) by what is written, or refused: no data line goes while a
flush awaits its proof, nor a job's line after an exception report until a
status report says where the board is; an internal fault writes nothing but
halts (no kill's fence either) and refuses a client's line, until
machine.reset; and out of a lockout machine.clear writes nothing.
"""

from __future__ import annotations

import pytest

from hostd.protocol.commands import Realtime
from hostd.protocol.errors import FaultActive
from hostd.protocol.stream import Stream
from hostd.protocol.vocabulary import Lane
from tests.protocol.g2wire import BUILDS, JOB_KILLERS, Wire


def ready(fb: float) -> Wire:
    wire = Wire(fb)
    wire.connect()
    return wire


def moves(n: int) -> Stream:
    return Stream(job_id=1).feed_all((i, f"G1 X{i % 100} F1000") for i in range(1, n + 1))


@pytest.mark.parametrize("fb", BUILDS)
def test_no_data_line_goes_until_the_board_shows_its_flush(fb: float) -> None:
    wire = ready(fb)
    wire.session.realtime(Realtime.QUEUE_FLUSH)
    wire.pump()
    wire.session.send("G0 X1", object())
    wire.pump()
    assert b"G0 X1\n" not in wire.lines()
    wire.report(stat=3)  # read after the `%` went out: the flush's proof
    assert wire.lines()[-1] == b"G0 X1\n"


@pytest.mark.parametrize("fb", BUILDS)
def test_a_jobs_lines_wait_for_a_report_after_an_exception(fb: float) -> None:
    wire = ready(fb)
    wire.session.start_stream(moves(50))
    wire.pump()
    written = len(wire.lines(Lane.DATA))
    wire.feed('{"er":{"fb":101.06,"st":107,"msg":"Input exceeds max length"}}')
    wire.answer(wire.unanswered[0])  # the job's first line: room for one more
    assert len(wire.lines(Lane.DATA)) == written  # room, but the board may be anywhere
    wire.report(stat=5)
    assert len(wire.lines(Lane.DATA)) == written + 1


@pytest.mark.parametrize("fb", BUILDS)
def test_a_halted_session_refuses_lines_and_writes_no_fence(fb: float) -> None:
    wire = ready(fb)
    wire.session.halt("books out of step")
    with pytest.raises(FaultActive):
        wire.session.send("G0 X1", object())
    wire.session.realtime(Realtime.JOB_KILL)  # a halt: it goes (101.02+: with its flush)
    wire.pump()
    assert wire.lines(Lane.DATA) == []  # no `$stat` fence behind the ^D
    assert wire.lines(Lane.REALTIME)[-1] == b"\x04\n"


@pytest.mark.parametrize("fb", BUILDS)
def test_machine_reset_ends_an_internal_fault(fb: float) -> None:
    wire = ready(fb)
    wire.session.halt("books out of step")
    wire.session.reset()
    wire.session.send("{xvm:n}", object())  # accepted again: no FaultActive


@pytest.mark.parametrize("fb", JOB_KILLERS)
def test_clear_outside_a_lockout_has_nothing_to_clear_and_writes_nothing(fb: float) -> None:
    wire = ready(fb)
    assert wire.session.clear(object()) is False
    wire.pump()
    assert b'{"clear":null}\n' not in wire.lines()
