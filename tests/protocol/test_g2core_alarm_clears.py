"""g2core's lockouts: what ends one, and what must not, byte by byte on the wire.

Each test pins one rule of g2lockouts.py (docs/protocol.md, "A clear waits for
the board's ALARM", "The alarm's own kill is not a new exception"): a clear
waits for a 101.05+ alarm's own job kill only when that kill is to come (not
for an alarm met inside a hold, which the board never turns into ALARM, nor
after kills of ours whose fences were all answered); an OK to a line that
clears does not end the lockout while the alarm's hold still runs; and a
kill's `er` 207 read in a lockout changes nothing (no ALARM over a SHUTDOWN,
no clear of hostd's own).
"""

from __future__ import annotations

import json

import pytest

from hostd.protocol.commands import Realtime
from hostd.protocol.errors import Rejected
from hostd.protocol.states import MachineState as S
from hostd.protocol.stream import Stream
from tests.protocol.g2wire import Wire

CLEAR = b'{"clear":null}\n'
LIMIT = '{"er":{"fb":%s,"st":203,"msg":"Limit hit - input 1"}}'
KILL_REPORT = '{"er":{"fb":%s,"st":207,"msg":"Kill job - Job killed by ^d"}}'


def ready(fb: float, **options: bool) -> Wire:
    wire = Wire(fb, **options)
    wire.connect()
    return wire


def written(wire: Wire) -> list[bytes]:
    return [data for _, data in wire.written]


@pytest.mark.parametrize("fb", [101.05, 101.06])
def test_a_clear_of_an_alarm_met_inside_a_hold_goes_at_once(fb: float) -> None:
    """An alarm read while the board already holds asks for a feedhold the board ignores
    (cycle_feedhold.cpp `cm_request_feedhold`, only from FEEDHOLD_OFF): no `_run_alarm`,
    no job kill of its own, no ALARM in any report. A clear waiting for those would
    wait forever, and the machine could never be freed."""
    wire = ready(fb)
    wire.report(stat=6, hold=4)  # the operator's `!`: the board holds
    wire.feed(LIMIT % fb)
    wire.answer_all()
    wire.report(stat=6, hold=4)
    assert wire.session.model.state is S.ALARM  # hostd's own lockout stands
    assert wire.session.clear(object())
    wire.pump()
    assert CLEAR in written(wire)


@pytest.mark.parametrize("fb", [101.05, 101.06])
def test_an_ok_to_a_clearing_line_in_the_alarms_hold_does_not_end_the_lockout(
    fb: float,
) -> None:
    """An M30 read before a 101.05+ alarm and answered during the alarm's hold cleared
    nothing: the board enters ALARM only once the hold has killed the job. The lockout
    stands through the hold's reports, and G-code is refused, not run inside the hold."""
    wire = ready(fb)
    wire.session.send("M30", object())
    wire.pump()
    assert b"M30\n" in wire.unanswered
    wire.feed(LIMIT % fb)
    wire.answer(b"M30\n", {})  # read before the alarm
    wire.answer_all()
    wire.report(stat=6, hold=4)  # the alarm's hold decelerates
    assert wire.session.model.state is S.ALARM
    with pytest.raises(Rejected) as refused:
        wire.session.send("G0 X1", object())
    assert refused.value.code == 204


@pytest.mark.parametrize("fb", [101.05, 101.06])
def test_a_clear_after_kills_that_merged_still_waits_for_a_later_alarms_hold(fb: float) -> None:
    """On two ports a ^D goes on each, and the board prints one 207 for both (one
    `_run_job_kill` clears every request, cycle_feedhold.cpp:553). Once both fences are
    answered no kill of ours is left to report: a later alarm's 207 is the board's own,
    and a clear asked during that alarm's hold waits for it (written then, cm_clear
    finds no ALARM yet and the clear is lost)."""
    wire = ready(fb, dual=True)
    stream = Stream().feed_all((i, f"G1 X{i} F1000") for i in range(1, 11))
    wire.session.start_stream(stream)
    wire.pump()
    wire.session.realtime(Realtime.JOB_KILL)
    wire.pump()
    wire.feed(KILL_REPORT % fb)  # both ^Ds, one kill
    wire.answer(b'{"stat":null}\n', {"stat": 4})
    wire.answer(b"$stat\n", {"stat": 4})
    assert not wire.session.flushing()
    wire.report(stat=4)
    wire.unanswered.clear()  # the job's lines the kill threw away
    wire.feed(LIMIT % fb)
    wire.answer_all()
    wire.report(stat=6, hold=4)  # the alarm's own hold
    assert wire.session.clear(object())
    wire.pump()
    assert CLEAR not in written(wire)
    wire.feed(KILL_REPORT % fb)  # `_run_alarm`: the board's kill, then ALARM
    wire.pump()
    assert CLEAR in written(wire)


def test_100_26_a_kill_report_in_a_shutdown_is_no_alarm_of_ours_and_is_not_cleared() -> None:
    """Before 101.02 hostd's ^D is an ALARM it clears itself once the lines it caught
    are answered. In a SHUTDOWN (an e-stop) a 207 says nothing new: taken for that
    ALARM, the state would read ALARM and hostd would write `{clear:n}` of its own,
    which cm_clear runs on a SHUTDOWN too (alarm.cpp:83-95)."""
    wire = ready(100.26)
    wire.feed('{"er":{"fb":100.26,"st":5,"msg":"Shutdown - input 2"}}')
    wire.answer_all()
    wire.report(stat=12)
    assert wire.session.model.state is S.SHUTDOWN
    wire.session.realtime(Realtime.JOB_KILL)  # the operator's cancel, in the shutdown
    wire.pump()
    wire.feed(json.dumps({"er": {"fb": 100.26, "st": 207, "msg": "Kill job - EOT Received"}}))
    wire.answer_all()
    wire.report(stat=12)
    wire.answer_all()
    assert wire.session.model.state is S.SHUTDOWN
    assert "Shutdown" in (wire.session.model.last_exception_message() or "")
    assert CLEAR not in written(wire)
