"""Every dialect's session (session.py): what a job start and a hold admit.

Rules SessionBase keeps for every dialect, shown here on grbl's session by
what reaches the board: a job starts only when no job runs and the state
admits an action (never in an alarm, whose unlock would then start it by
itself); a line of an operation that has ended is not written; and a hold
begun after a resume is a hold again, whatever its `~` left behind: grbl
runs no line inside it, so a client's line is refused on the host.
"""

from __future__ import annotations

import pytest

from hostd.protocol.commands import Realtime
from hostd.protocol.errors import Busy, Rejected
from hostd.protocol.vocabulary import Lane, Settled
from tests.protocol.test_grbl_session import Grbl, moves

HOLD_0 = "<Hold:0|MPos:0.000,0.000,0.000|FS:0,0>"


def test_a_second_job_is_refused_while_one_runs() -> None:
    grbl = Grbl()
    grbl.connect()
    first = moves(50)
    grbl.session.start_stream(first)
    grbl.pump()
    with pytest.raises(Busy, match="running a job"):
        grbl.session.start_stream(moves(5))
    assert grbl.session.stream is first and not first.done


def test_a_job_is_not_started_in_an_alarm_nor_run_by_its_unlock() -> None:
    grbl = Grbl()
    grbl.connect()
    grbl.feed("ALARM:9", "<Alarm|MPos:0.000,0.000,0.000|FS:0,0>")
    with pytest.raises(Rejected) as refused:
        grbl.session.start_stream(moves(5))
    assert refused.value.code == 204
    assert grbl.session.clear(object())
    grbl.pump()
    grbl.feed("ok", "<Idle|MPos:0.000,0.000,0.000|FS:0,0>")
    assert grbl.lines() == [b"$X\n"]


def test_a_line_of_an_operation_that_ended_is_not_written() -> None:
    grbl = Grbl()
    grbl.connect()
    grbl.session.set_operation(True)
    grbl.session.send("$110=600", object(), operation=True)
    token = object()
    grbl.session.send("G0 X5", token, operation=True)  # waits: the setting writes EEPROM
    assert grbl.pump() == [(Lane.DATA, b"$110=600\n")]
    grbl.session.set_operation(False)  # the operation ended (cancelled) meanwhile
    grbl.feed("ok")
    assert grbl.lines() == [b"$110=600\n"]
    settled = grbl.settled(token)
    assert isinstance(settled, Settled) and isinstance(settled.outcome, Busy)


def test_a_hold_begun_after_a_resume_refuses_lines_again() -> None:
    """`!`, `~`, `!` again before any report showed the board out of its hold: it
    holds, and a line sent now would wait in its buffer to run at the next resume."""
    grbl = Grbl()
    grbl.connect()
    grbl.session.realtime(Realtime.FEEDHOLD)
    grbl.pump()
    grbl.feed(HOLD_0)
    grbl.session.realtime(Realtime.CYCLE_START)
    grbl.session.realtime(Realtime.FEEDHOLD)
    grbl.pump()
    grbl.feed(HOLD_0)
    with pytest.raises(Busy, match="grbl runs no line inside"):
        grbl.session.send("G0 X1", object())
    grbl.pump()
    assert grbl.lines() == []
