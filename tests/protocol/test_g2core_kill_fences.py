"""g2core's kills and flushes: what waits for their proof, byte by byte on the wire.

Each test pins one rule of g2kills.py and g2flow.py (docs/protocol.md, "A kill's
fence"): on two ports a kill's wait ends only with both fences answered, the
control port's too; a job's `{`-line never overtakes a kill's fence still
unread, even once the flush's timeout let data lines go again; an in-hold line
waits while the board may be anywhere (a flush unproven, an exception report
not yet followed by a status report); and a session with a flush under way is
not quiet (its caller would take the board for at rest and idle).
"""

from __future__ import annotations

import pytest

from hostd.protocol.commands import Realtime
from hostd.protocol.g2kills import FLUSH_CONFIRM_TIMEOUT
from hostd.protocol.stream import Stream
from hostd.protocol.vocabulary import Lane
from tests.protocol.g2wire import BUILDS, JOB_KILLERS, Wire

FENCE = b"$stat\n"
CONTROL_FENCE = b'{"stat":null}\n'
OUT4 = b'{"out4":1}\n'
TOO_LONG = '{"er":{"fb":%s,"st":107,"msg":"Input exceeds max length"}}'


def ready(fb: float, **options: bool) -> Wire:
    wire = Wire(fb, **options)
    wire.connect()
    return wire


@pytest.mark.parametrize("fb", JOB_KILLERS)
def test_on_two_ports_no_data_line_goes_until_the_control_ports_fence_is_answered(
    fb: float,
) -> None:
    """The control port's `{"stat":null}` answered says its ^D was read: before then that
    ^D may still reach the board and kill what is sent meanwhile. The data port's fence
    can be answered first (the board reads ports in turn): the wait goes on."""
    wire = ready(fb, dual=True)
    wire.session.realtime(Realtime.JOB_KILL)
    wire.pump()
    assert (Lane.CONTROL, CONTROL_FENCE) in wire.written
    wire.answer(FENCE, {"stat": 4})  # the data port's fence, read first
    wire.session.send("G0 X1", object())
    wire.pump()
    assert wire.session.flushing()
    assert b"G0 X1\n" not in wire.lines()
    wire.answer(CONTROL_FENCE, {"stat": 4})
    assert not wire.session.flushing()
    assert wire.lines()[-1] == b"G0 X1\n"


@pytest.mark.parametrize("fb", JOB_KILLERS)
def test_a_jobs_json_line_waits_for_a_kills_fence_still_unread_after_the_timeout(
    fb: float,
) -> None:
    """After the flush's timeout data lines go again, behind the unread fence. A `{`-line
    would not: the board reads it ahead of the data lines waiting on its port
    (xio.cpp:789), so ahead of the ^D's fence; it goes once the fence is answered."""
    wire = ready(fb)
    wire.session.realtime(Realtime.JOB_KILL)
    wire.pump()
    wire.at(FLUSH_CONFIRM_TIMEOUT + 1)  # no proof: the wait ends, the fence stays booked
    assert not wire.session.flushing()
    wire.answer_all(data=False)  # the heartbeat's query, a silent board being asked
    job = Stream(job_id=1).feed_all([(1, '{"out4":1}'), (2, "G1 X1 F100")])
    wire.session.start_stream(job)
    wire.pump()
    assert OUT4 not in wire.lines()
    wire.answer(FENCE, {"stat": 4})
    assert OUT4 in wire.lines()


@pytest.mark.parametrize("fb", JOB_KILLERS)
def test_an_in_hold_line_waits_for_a_report_after_an_exception(fb: float) -> None:
    """In a hold a client's G-code goes at once as `gc2`, to run inside the hold. After an
    exception report the board may have left the hold (or be entering a lockout): the
    line waits for a status report, which shows whether the hold is still on."""
    wire = ready(fb)
    wire.report(stat=6, hold=4)
    wire.feed(TOO_LONG % fb)
    wire.session.send("G0 X1", object())
    wire.pump()
    assert not [x for x in wire.lines() if x.startswith(b'{"gc2"')]
    wire.report(stat=6, hold=4)
    assert wire.lines()[-1].startswith(b'{"gc2"')


@pytest.mark.parametrize("fb", JOB_KILLERS)
def test_an_in_hold_line_waits_while_a_flush_awaits_its_proof(fb: float) -> None:
    wire = ready(fb)
    wire.report(stat=6, hold=4)
    wire.session.realtime(Realtime.QUEUE_FLUSH)
    wire.pump()
    wire.session.send("G0 X1", object())
    wire.pump()
    assert not [x for x in wire.lines() if x.startswith(b'{"gc2"')]


@pytest.mark.parametrize("fb", BUILDS)
def test_a_session_whose_flush_is_unproven_is_not_quiet(fb: float) -> None:
    """`quiet` is what the machine layer takes for "nothing of ours under way" (the board
    at rest, hostd/machine/rest.py). A `%` at rest leaves nothing queued or unanswered,
    but until a stop read after it shows the flush, a line sent would be thrown away."""
    wire = ready(fb)
    assert wire.session.quiet()
    wire.session.realtime(Realtime.QUEUE_FLUSH)
    wire.pump()
    assert not wire.session.quiet()
    wire.report(stat=3)
    assert wire.session.quiet()
