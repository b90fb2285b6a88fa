"""g2core's reports: which of them move the session, and the heartbeat they answer.

Pins two rules of g2status.py and g2connection.py: a lockout hostd holds (an
alarm announced, the board still in the alarm's hold) ends only with a report
that carries a `stat` showing it, never with one that leaves `stat` out (a
filtered automatic report of a position); and a board that answers the
heartbeat's status request is alive: it is not given up as silent.
"""

from __future__ import annotations

import pytest

from hostd.protocol.errors import Rejected
from hostd.protocol.states import MachineState as S
from hostd.protocol.vocabulary import Closing, Lane
from tests.protocol.g2wire import BUILDS, Wire

LIMIT = '{"er":{"fb":%s,"st":203,"msg":"Limit hit - input 1"}}'


@pytest.mark.parametrize("fb", [101.05, 101.06])
def test_a_report_without_stat_does_not_end_the_lockout_of_an_alarms_hold(fb: float) -> None:
    wire = Wire(fb)
    wire.connect()
    wire.feed(LIMIT % fb)
    wire.answer_all()
    wire.report(posx=1.5)  # filtered: only what changed, no `stat`
    wire.report(stat=6, hold=4)  # the alarm's hold decelerates
    assert wire.session.model.state is S.ALARM
    with pytest.raises(Rejected) as refused:
        wire.session.send("G0 X1", object())
    assert refused.value.code == 204


@pytest.mark.parametrize("fb", BUILDS)
def test_a_board_that_answers_the_heartbeat_is_not_given_up(fb: float) -> None:
    wire = Wire(fb, heartbeat=2.0)
    wire.connect()
    assert wire.at(2.0) == [(Lane.CONTROL, b'{"sr":null}\n')]
    wire.at(2.5)
    wire.answer(b'{"sr":null}\n')  # alive
    wire.at(4.0)  # the deadline the unanswered request had
    wire.at(4.4)
    assert wire.of(Closing) == []
