"""g2core's session on each firmware build, by plain calls (hostd/protocol/g2builds.py).

Kills, flushes, alarms and holds differ between builds; each rule is run on
every build it applies to, and its opposite on the others. docs/protocol.md
has the table, with the source lines each rests on.
"""

from __future__ import annotations

import json

import pytest

from hostd.protocol.commands import InvalidCommand, Realtime
from hostd.protocol.errors import Busy, Rejected
from hostd.protocol.g2kills import FLUSH_CONFIRM_TIMEOUT
from hostd.protocol.states import MachineState as S
from hostd.protocol.stream import Stream
from hostd.protocol.vocabulary import Detected, Excepted, Lane, StreamEnd
from tests.protocol.g2wire import BUILDS, JOB_KILLERS, Wire, banner

KILL = b"\x04\n"
FENCE = b"$stat\n"  # behind each ^D on the data port (g2kills.py `_write_fence`)
CONTROL_FENCE = b'{"stat":null}\n'  # behind the control port's ^D, on two ports
CLEAR = b'{"clear":null}\n'
LIMIT = '{"er":{"fb":%s,"st":203,"msg":"Limit hit - input 1"}}'


def moves(n: int) -> Stream:
    return Stream().feed_all(enumerate((f"G1 X{i % 100} F1000" for i in range(n)), start=1))


def ready(fb: float, **options: object) -> Wire:
    wire = Wire(fb, **options)  # type: ignore[arg-type]
    wire.connect()
    return wire


def streaming(fb: float, **options: object) -> tuple[Wire, Stream]:
    """A board of build `fb` running a job of 20 moves, its first window written."""
    wire = ready(fb, **options)
    stream = moves(20)
    wire.session.start_stream(stream)
    wire.pump()
    return wire, stream


def kill_report(fb: float) -> str:
    msg = "Kill job - EOT Received" if fb < 101.02 else "Kill job - Job killed by ^d"
    return json.dumps({"er": {"fb": fb, "st": 207, "msg": msg}})


def data_lines(wire: Wire) -> list[bytes]:
    return [x for x in wire.unanswered if not x.startswith((b"{", b"$"))]  # `$`: fences


def faults(wire: Wire) -> list[Detected]:
    return wire.of(Detected)


def fenced(wire: Wire) -> None:
    """The board reads a kill's fences: the control port's first, then the data port's."""
    if CONTROL_FENCE in wire.unanswered:
        wire.answer(CONTROL_FENCE, {"stat": 4})
    wire.answer(FENCE, {"stat": 4})


# -- item 1: a kill on two ports goes on both, and is settled by the data port's fence ----


@pytest.mark.parametrize("fb", JOB_KILLERS)
def test_a_kill_on_two_ports_is_written_on_both_and_waits_for_the_data_ports_fence(
    fb: float,
) -> None:
    wire, stream = streaming(fb, dual=True)
    sent = data_lines(wire)
    assert len(sent) == 4
    wire.session.realtime(Realtime.JOB_KILL)
    wire.pump()
    assert wire.written[-4:] == [
        (Lane.REALTIME, KILL),
        (Lane.DATA, KILL),
        (Lane.DATA, FENCE),
        (Lane.CONTROL, CONTROL_FENCE),
    ]
    wire.feed(kill_report(fb))  # the control port's kill: the data port was not flushed
    wire.answer(CONTROL_FENCE, {"stat": 4})  # the control port's ^D was read
    assert stream.discarded == 0 and wire.session.flushing()
    wire.answer(sent[0], {})  # read from the data port before its own ^D: matched
    wire.feed(kill_report(fb))  # the data port's kill
    assert wire.session.flushing() and stream.discarded == 0  # its fence is not read yet
    wire.answer(FENCE, {"stat": 4})  # read after the ^D: the rest were thrown away
    assert not wire.session.flushing()
    assert stream.acked == 1 and stream.discarded == 3
    assert stream.result.end is StreamEnd.CANCELLED
    assert wire.session.unanswered() == 0
    assert faults(wire) == []


@pytest.mark.parametrize("fb", JOB_KILLERS)
def test_a_kill_on_one_port_is_written_once_and_settled_by_its_fence(fb: float) -> None:
    wire, stream = streaming(fb)
    wire.session.realtime(Realtime.JOB_KILL)
    wire.pump()
    assert wire.written[-2:] == [(Lane.REALTIME, KILL), (Lane.DATA, FENCE)]
    wire.feed(kill_report(fb))
    assert wire.session.flushing()
    fenced(wire)
    assert not wire.session.flushing() and stream.discarded == 4


@pytest.mark.parametrize("fb", JOB_KILLERS)
@pytest.mark.parametrize("dual", [False, True], ids=["one-port", "two-ports"])
def test_kills_that_merge_into_one_report_leave_nothing_on_the_books(fb: float, dual: bool) -> None:
    """cm_request_job_kill only sets a flag (cycle_feedhold.cpp:523) and one `_run_job_kill`
    clears it with one 207 (:551-553): a ^D read before the kill ran adds no report. The
    ^Ds still threw away what each port held unread (controller.cpp:282)."""
    wire, stream = streaming(fb, dual=dual)
    sent = data_lines(wire)
    wire.answer(sent[0], {})  # read before the kill
    wire.session.realtime(Realtime.JOB_KILL)
    wire.session.realtime(Realtime.JOB_KILL)  # a second cancel while the first one holds
    wire.pump()
    assert [x for x in wire.unanswered if x.startswith(b"$")] == [FENCE, b"$line\n"]
    wire.feed(kill_report(fb))  # every ^D read before the hold ended: one report
    for line in [*data_lines(wire), FENCE]:
        # Thrown away unread: the job's lines by the first ^D, the first kill's fence by
        # the second ^D, read ahead of it (controls first) once the hold has ended.
        wire.unanswered.remove(line)
    while CONTROL_FENCE in wire.unanswered:
        wire.answer(CONTROL_FENCE, {"stat": 4})
    assert wire.session.flushing()
    wire.answer(b"$line\n", {"line": 0})  # the second kill's fence, another key
    wire.at(FLUSH_CONFIRM_TIMEOUT + 1)  # no other report comes
    wire.answer_all(data=False)  # the heartbeat's query, a silent board being asked
    assert not wire.session.flushing()
    assert stream.sent == 5 and stream.acked == 1 and stream.discarded == 4
    assert wire.session.unanswered() == 0  # nothing left on the books
    assert faults(wire) == []
    # The window is free: a new job's lines go out, and each answer is its own.
    wire.report(stat=4)
    again = moves(6)
    wire.session.start_stream(again)
    wire.pump()
    assert len(data_lines(wire)) == 4
    wire.answer_all()
    wire.answer_all()
    wire.report(stat=4)
    assert again.acked == 6 and again.result.end is StreamEnd.COMPLETED
    assert faults(wire) == []


@pytest.mark.parametrize("fb", JOB_KILLERS)
def test_two_kills_fences_are_told_apart_and_the_last_ends_the_wait(fb: float) -> None:
    """The first kill's fence may be read before the second ^D comes in, or be thrown
    away by it: each asks for another key, and only the last one's answer ends it."""
    wire, stream = streaming(fb)
    wire.session.realtime(Realtime.JOB_KILL)
    wire.session.realtime(Realtime.JOB_KILL)
    wire.pump()
    assert [d for _, d in wire.written if d.startswith(b"$")] == [FENCE, b"$line\n"]
    wire.feed(kill_report(fb))
    wire.answer(FENCE, {"stat": 4})  # read before the second ^D came in
    assert stream.discarded == 4 and wire.session.flushing()
    wire.feed(kill_report(fb))  # the second kill, at rest
    wire.answer(b"$line\n", {"line": 0})
    assert not wire.session.flushing() and wire.session.unanswered() == 0
    assert faults(wire) == []


@pytest.mark.parametrize("fb", JOB_KILLERS)
def test_a_line_the_data_port_reads_after_the_kill_and_the_timeout_is_still_its_own(
    fb: float,
) -> None:
    """The control port's ^D can be read, and its kill run, before the data port's ^D has
    reached the board: until the fence behind that ^D is answered, a line written before
    it may yet be read and answered, so none is booked discarded before then, the flush's
    timeout passing or not."""
    wire, stream = streaming(fb, dual=True)
    sent = data_lines(wire)
    wire.session.realtime(Realtime.JOB_KILL)
    wire.pump()
    wire.feed(kill_report(fb))  # the control port's kill
    wire.at(FLUSH_CONFIRM_TIMEOUT + 1)
    wire.answer(b'{"sr":null}\n')  # the heartbeat's query, a silent board being asked
    assert stream.discarded == 0 and wire.session.unanswered() == 5
    wire.answer(sent[0], {})  # read before the data port's ^D came in
    wire.answer(sent[1], {})
    assert stream.acked == 2 and stream.discarded == 0
    wire.feed(kill_report(fb))  # the data port's kill
    fenced(wire)
    assert stream.acked == 2 and stream.discarded == 2
    assert wire.session.unanswered() == 0 and faults(wire) == []


@pytest.mark.parametrize("fb", JOB_KILLERS)
def test_a_kill_in_a_lockout_is_settled_by_its_fence_with_no_report(fb: float) -> None:
    """In ALARM, SHUTDOWN or PANIC a ^D kills nothing and prints nothing
    (cycle_feedhold.cpp:561-565), but it still throws away what its port holds unread."""
    wire = ready(fb, dual=True)
    token = object()
    wire.session.send("G0 X1", token)
    wire.pump()
    wire.report(stat=2)
    wire.session.realtime(Realtime.JOB_KILL)
    wire.pump()
    fenced(wire)
    assert not wire.session.flushing() and wire.session.unanswered() == 0
    settled = wire.settled(token)
    assert settled is not None and "discarded" in str(settled.outcome)


@pytest.mark.parametrize("fb", JOB_KILLERS)
def test_a_query_of_stat_during_a_kill_is_its_clients_and_no_fence(fb: float) -> None:
    """The control port is read on every pass, the data port only between holds: a
    client's `{stat:n}` is answered while the data port's fence waits, and is not taken
    for it (its answer's count is its own)."""
    wire, stream = streaming(fb, dual=True)
    wire.session.realtime(Realtime.JOB_KILL)
    wire.pump()
    token = object()
    wire.session.send("{stat:n}", token)  # a client's query of the same key
    wire.pump()
    assert wire.written[-1] == (Lane.CONTROL, CONTROL_FENCE)  # sent as strict JSON
    wire.answer(CONTROL_FENCE, {"stat": 6})  # the control port's fence, then the query
    wire.answer(CONTROL_FENCE, {"stat": 6})
    settled = wire.settled(token)
    assert settled is not None and settled.outcome.body == {"stat": 6}  # type: ignore[union-attr]
    assert wire.session.flushing() and stream.discarded == 0
    wire.feed(kill_report(fb), kill_report(fb))
    wire.answer(FENCE, {"stat": 4})
    assert not wire.session.flushing() and stream.discarded == 4
    assert faults(wire) == []


@pytest.mark.parametrize("fb", [100.26, 101.03])
def test_a_flush_on_two_ports_before_101_05_flushes_the_data_port_too(fb: float) -> None:
    """`%` flushes its own port (xio_flush_to_command); only 101.05+ flushes every data port
    once held, so older builds get `!` `%` on the data port as well (a `%` after `!` is a
    flush even at rest)."""
    wire = ready(fb, dual=True)
    wire.session.realtime(Realtime.QUEUE_FLUSH)
    wire.pump()
    assert wire.written[-2:] == [(Lane.DATA, b"!\n"), (Lane.DATA, b"%\n")]


def test_a_flush_on_two_ports_on_101_06_goes_on_the_control_port_alone() -> None:
    wire = ready(101.06, dual=True)
    wire.session.realtime(Realtime.QUEUE_FLUSH)
    wire.pump()
    assert wire.written == [(Lane.REALTIME, b"%\n")]  # a `!` at rest would hold it


# -- item 5: before 101.02 ^D is an ALARM and every caught line is answered 204 ------------


def test_before_101_02_a_cancel_is_settled_by_the_204s_then_cleared() -> None:
    wire, stream = streaming(100.26, dual=True)
    sent = data_lines(wire)
    wire.session.realtime(Realtime.JOB_KILL)
    wire.pump()
    assert [x for x in wire.written if x[1] == KILL] == [(Lane.REALTIME, KILL)]
    assert stream.result.end is StreamEnd.CANCELLED
    wire.feed(kill_report(100.26))
    assert wire.session.model.state is S.ALARM
    assert CLEAR not in wire.lines()  # not while lines it would clear behind are unanswered
    for line in sent:
        wire.answer(line, {}, status=204)
    assert stream.discarded == 4 and stream.rejected == 0
    assert faults(wire) == []
    assert (Lane.DATA, CLEAR) in wire.written
    wire.answer(CLEAR, {"clear": None})
    wire.answer_all()
    wire.report(stat=3)
    assert wire.session.model.state is S.PROGRAM_STOP


def test_before_101_02_no_g_code_runs_inside_a_hold() -> None:
    wire = ready(100.26)
    wire.report(stat=6, hold=10)
    with pytest.raises(Busy, match="gc2"):
        wire.session.send("G0 X1", object())


# -- items 2 and 3: 101.06 alarms arrive through a hold --------------------------------


def test_101_06_the_lockout_stands_through_the_alarms_hold_and_keeps_its_reason() -> None:
    wire, _ = streaming(101.06)
    written = len(wire.written)
    wire.feed(LIMIT % 101.06)
    wire.report(stat=6, hold=4)  # the alarm's feedhold decelerates
    assert wire.session.model.state is S.ALARM
    with pytest.raises(Rejected) as refused:
        wire.session.send("G0 X1", object())
    assert refused.value.code == 204 and "Limit hit" in refused.value.message
    wire.report(stat=6, hold=10)
    wire.feed(kill_report(101.06))  # `_run_alarm`: the board's own job kill
    assert "Limit hit" in wire.session.model.last_exception_message()  # type: ignore[operator]
    assert [e.fields["st"] for e in wire.of(Excepted)] == [203]
    wire.report(stat=2, hold=0)
    assert wire.session.model.state is S.ALARM
    with pytest.raises(Rejected, match="Limit hit"):
        wire.session.send("G0 X1", object())
    assert not [x for _, x in wire.written[written:] if x.startswith((b"G", b'{"gc'))]


def test_101_06_the_alarms_own_kill_does_not_settle_a_kill_of_ours() -> None:
    wire, stream = streaming(101.06)
    wire.feed(LIMIT % 101.06)
    wire.session.realtime(Realtime.JOB_KILL)  # a kill in ALARM: the board ignores it
    wire.pump()
    wire.feed(kill_report(101.06))  # the alarm's, not ours
    assert wire.session.flushing()
    assert stream.discarded == 0


# -- item 4: 101.02-101.04 never enter ALARM: hostd stops the board and keeps the lockout --


def test_101_03_an_alarm_is_stopped_by_hostd_and_held_until_a_clear() -> None:
    wire, stream = streaming(101.03)
    wire.feed(LIMIT % 101.03)
    assert (Lane.REALTIME, KILL) in wire.written  # the board would run the next line read
    assert stream.result.code == 204
    wire.feed(kill_report(101.03))  # our kill ran
    fenced(wire)  # read after it: what it flushed is dropped
    assert not wire.session.flushing() and stream.discarded == 4
    wire.report(stat=4, hold=0)  # the board shows no alarm: hostd's lockout stands
    assert wire.session.model.state is S.ALARM
    assert "Limit hit" in (wire.session.model.last_exception_message() or "")
    with pytest.raises(Rejected):
        wire.session.send("G0 X1", object())
    token = object()
    assert wire.session.clear(token)
    wire.pump()
    assert (Lane.DATA, CLEAR) in wire.written
    wire.answer(CLEAR, {"clear": None})
    wire.answer_all()
    wire.report(stat=4)
    assert wire.session.model.state is S.PROGRAM_END
    wire.session.send("G0 X1", object())  # free again


@pytest.mark.parametrize("fb", [100.26, 101.06])
def test_a_board_that_enters_alarm_itself_is_not_killed_by_hostd(fb: float) -> None:
    wire = ready(fb)
    wire.session.start_stream(moves(20))
    wire.pump()
    wire.feed(LIMIT % fb)
    assert KILL not in [d for _, d in wire.written]


# -- item 6: a board that holds is in a hold, whatever its stat says --------------------


@pytest.mark.parametrize("fb", BUILDS)
def test_a_hold_shown_only_by_the_hold_field_stops_job_lines(fb: float) -> None:
    wire = ready(fb)
    wire.report(stat=3, hold=10)  # 101.06: `!` at rest; stat is unchanged
    stream = moves(5)
    wire.session.start_stream(stream)
    wire.pump()
    assert data_lines(wire) == []
    wire.report(hold=0)
    assert len(data_lines(wire)) == 4


def test_101_06_a_line_sent_in_a_hold_at_rest_runs_inside_it() -> None:
    wire = ready(101.06)
    wire.report(stat=3, hold=10)
    wire.session.send("G0 X1", object())
    wire.pump()
    assert wire.lines() == [b'{"gc2":"G0 X1"}\n']


# -- item 8: the clear goes on the data port ------------------------------------------


@pytest.mark.parametrize("fb", BUILDS)
def test_a_clear_is_written_on_the_data_lane(fb: float) -> None:
    wire = ready(fb, dual=True)
    wire.report(stat=2)
    assert wire.session.clear(object())
    wire.pump()
    assert wire.written == [(Lane.DATA, CLEAR)]


# -- item 9: smaller ------------------------------------------------------------------


@pytest.mark.parametrize("fb", BUILDS)
def test_a_204_answer_alone_locks_out(fb: float) -> None:
    wire = ready(fb)
    token = object()
    wire.session.send("G0 X1", token)
    wire.pump()
    wire.answer(b"G0 X1\n", {}, status=204)
    assert wire.session.model.state is S.ALARM
    with pytest.raises(Rejected):
        wire.session.send("G0 X2", object())


def test_an_unconfirmed_kill_on_two_ports_gives_up_after_its_timeout() -> None:
    wire = ready(101.06, dual=True)
    wire.session.start_stream(moves(20))
    wire.pump()
    wire.session.realtime(Realtime.JOB_KILL)
    wire.pump()
    wire.feed(kill_report(101.06))
    wire.at(FLUSH_CONFIRM_TIMEOUT + 1)
    assert not wire.session.flushing()


@pytest.mark.parametrize("fb", BUILDS)
def test_a_planner_starved_mid_job_is_an_underflow_naming_the_line(fb: float) -> None:
    wire, _ = streaming(fb)
    wire.report(stat=5, mpox=0.5, vel=1000)
    for line in data_lines(wire)[:2]:
        wire.answer(line, {})
    wire.report(stat=3, mpox=1, vel=0)  # the board stopped with the job's lines on the host
    assert [(d.fault, d.value) for d in faults(wire)] == [("underflow", 2)]
    assert "after file line 2" in faults(wire)[0].message


@pytest.mark.parametrize("fb", BUILDS)
def test_a_run_seen_moving_only_in_its_final_report_is_still_an_underflow(fb: float) -> None:
    """A short run can end before any report in between: the stop's report (g2core's
    final one, canonical_machine.cpp:1686) says where it went."""
    wire, _ = streaming(fb)
    wire.report(stat=5)
    wire.answer(data_lines(wire)[0], {})
    wire.report(stat=3, mpox=1)
    assert [(d.fault, d.value) for d in faults(wire)] == [("underflow", 1)]


@pytest.mark.parametrize("fb", BUILDS)
def test_a_stop_where_nothing_moved_is_no_underflow_and_a_later_starving_one_is(
    fb: float,
) -> None:
    """A job at rest whose first lines move nothing (a resume's preamble, its approach
    to where the tool already is: g2core drops a zero-length move and ends the cycle
    it started, canonical_machine.cpp:1204-1211) runs out of lines before the host's
    next come: nothing starved, nothing to report. A run that moves and starves, later
    in the same job, still is an underflow."""
    wire = ready(fb)
    wire.report(stat=1, mpox=5, mpoy=0, mpoz=0, vel=0)  # at rest, at X5
    lines = ["G21 G90", "G0 X5 Y0 Z0", "G1 Z0 F300", "G1 X6 F1000", "G1 X7"]
    stream = Stream()
    stream.feed_many(enumerate(lines[:3], start=1))  # the rest not read from the file yet
    wire.session.start_stream(stream)
    wire.pump()
    wire.report(stat=5)  # the zero-length moves start a cycle...
    wire.answer_all()
    wire.report(stat=3)  # ...and end it where it stood
    assert faults(wire) == [] and not stream.done
    stream.feed_many(enumerate(lines[3:], start=4))
    wire.pump()
    wire.report(stat=5, mpox=5.5, vel=1000)
    wire.answer(data_lines(wire)[0], {})
    wire.report(stat=3, mpox=6, vel=0)  # moved, and stopped with X7 on the host
    assert [(d.fault, d.value) for d in faults(wire)] == [("underflow", 4)]


@pytest.mark.parametrize("fb", BUILDS)
def test_a_stop_before_a_jobs_json_line_is_no_underflow(fb: float) -> None:
    """The `{`-line waits for the lines before it: the planner drains there on purpose."""
    wire = ready(fb)
    stream = Stream().feed_all(enumerate(["G1 X1 F100", '{"out4":1}', "G1 X2"], start=1))
    wire.session.start_stream(stream)
    wire.pump()
    wire.report(stat=5)
    wire.report(stat=3)
    assert faults(wire) == []


def test_101_03_an_m30_that_the_board_ran_ends_hostds_lockout() -> None:
    """101.03 never enters ALARM: an M30 (a clear in the class table) runs as a plain line,
    and its OK ends the lockout hostd kept."""
    wire = ready(101.03)
    wire.feed(LIMIT % 101.03)
    wire.feed(kill_report(101.03))
    wire.answer_all()
    wire.report(stat=4)
    assert wire.session.model.state is S.ALARM
    wire.session.send("M30", object())
    wire.pump()
    wire.answer(b"M30\n", {})
    wire.answer_all()
    wire.report(stat=4)
    assert wire.session.model.state is S.PROGRAM_END


def _clear_asked_in_the_alarms_hold() -> Wire:
    """A 101.06 board decelerating in a limit alarm's hold, asked to clear: not written."""
    wire = ready(101.06)
    wire.feed(LIMIT % 101.06)
    wire.answer_all()
    wire.report(stat=6, hold=4)
    assert wire.session.clear(object())
    wire.pump()
    assert CLEAR not in [x for _, x in wire.written]  # kept back: the hold still runs
    return wire


def test_101_06_a_clear_asked_during_the_alarms_hold_waits_for_the_alarm_then_ends_it() -> None:
    """cm_clear finds no ALARM while the alarm's hold runs (alarm.cpp:83): written then,
    it would be answered OK and do nothing, and the board enter ALARM after it. The
    clear waits for the board's own job kill, after which it is in ALARM
    (cycle_feedhold.cpp `_run_alarm`), and then ends the lockout."""
    wire = _clear_asked_in_the_alarms_hold()
    wire.report(stat=6, hold=10)
    wire.pump()
    assert CLEAR not in [x for _, x in wire.written]
    wire.feed(kill_report(101.06))  # `_run_alarm`: the kill, then MACHINE_ALARM
    wire.pump()
    assert CLEAR in [x for _, x in wire.written]
    wire.answer(CLEAR, {"clear": None})
    wire.answer_all()
    wire.report(stat=3, hold=0)  # cm_clear: PROGRAM_STOP
    assert wire.session.model.state is S.PROGRAM_STOP


def test_101_06_a_clear_waiting_for_the_alarm_goes_when_a_report_shows_it() -> None:
    """The board's ALARM in a report is proof enough, whether or not its 207 was read."""
    wire = _clear_asked_in_the_alarms_hold()
    wire.report(stat=2, hold=0)
    wire.pump()
    assert CLEAR in [x for _, x in wire.written]


@pytest.mark.parametrize(
    ("fb", "detail", "lockout"),
    [
        (100.26, "encoder_test_assertions()", S.PANIC),  # encoder.cpp:64, the only 92
        (101.03, "encoder_test_assertions()", S.PANIC),
        (101.06, "encoder_test_assertions()", S.PANIC),
        (101.06, "encoder stopped returning values", S.ALARM),  # kinematics_four_cable.h:684
    ],
)
def test_status_92_is_a_panic_where_the_source_says_so(fb: float, detail: str, lockout: S) -> None:
    wire = ready(fb)
    msg = f"Encoder assertion failure - {detail}"
    wire.feed(json.dumps({"er": {"fb": fb, "st": 92, "msg": msg}}))
    assert wire.session.model.state is lockout


@pytest.mark.parametrize("fb", JOB_KILLERS)
def test_the_kill_after_a_refused_job_line_goes_on_both_ports_too(fb: float) -> None:
    wire, stream = streaming(fb, dual=True)
    first, *rest = data_lines(wire)
    wire.answer(first, {}, status=133)  # modal group violation: the job fails, the rest is killed
    assert stream.result.end is StreamEnd.FAILED
    assert (Lane.REALTIME, KILL) in wire.written and (Lane.DATA, KILL) in wire.written
    wire.feed(kill_report(fb))
    assert wire.session.flushing()  # the data port's kill is still to come
    wire.feed(kill_report(fb))
    fenced(wire)
    assert stream.discarded == len(rest) and faults(wire) == []


# -- overrides: the build's settings (g2builds.py override_keys) ------------------------

OVERRIDE_LINES = {
    100.26: (b'{"mfo":null,"mto":null,"sso":null}\n', b'{"mfoe":1,"mfo":1.5,"ssoe":1,"sso":0.8}\n'),
    101.03: (b'{"fro":null,"tro":null,"spo":null}\n', b'{"fro":1.5,"spoe":1,"spo":0.8}\n'),
    101.06: (b'{"fro":null,"tro":null,"spo":null}\n', b'{"fro":1.5,"spoe":1,"spo":0.8}\n'),
}


@pytest.mark.parametrize("fb", BUILDS)
def test_overrides_are_read_and_written_as_the_build_names_them(fb: float) -> None:
    read, write = OVERRIDE_LINES[fb]
    wire = Wire(fb)
    wire.session.open()
    wire.pump()
    wire.feed(banner(fb))
    while read not in wire.unanswered:
        wire.answer(wire.unanswered[0])
    wire.answer(read, dict.fromkeys(json.loads(read), 1.0))  # asked in the handshake
    while not wire.session.ready:
        wire.answer(wire.unanswered[0])
    assert wire.session.model.overrides == {"feed": 100.0, "rapid": 100.0, "spindle": 100.0}
    seen = wire.session.model.override_reports
    wire.session.override(feed=150, spindle=80)
    wire.pump()
    assert (Lane.CONTROL, write) in wire.written
    wire.answer(write, {k: v for k, v in json.loads(write).items()})
    assert wire.session.model.overrides == {"feed": 150.0, "rapid": 100.0, "spindle": 80.0}
    assert wire.session.model.override_reports == seen + 1


@pytest.mark.parametrize("fb", BUILDS)
def test_an_override_out_of_the_firmwares_bounds_writes_nothing(fb: float) -> None:
    wire = ready(fb)
    for asked in ({"rapid": 150}, {"feed": 201}, {"spindle": 4}):
        with pytest.raises(InvalidCommand):
            wire.session.override(**asked)
    wire.session.override(rapid=5)
    assert not any(b"150" in line or b"2.01" in line for line in wire.lines())


def test_a_program_end_puts_feed_and_rapid_back_as_the_board_does() -> None:
    wire = ready(101.06)
    wire.session.override(feed=150, rapid=50, spindle=80)
    wire.pump()
    wire.answer_all()
    assert wire.session.model.overrides == {"feed": 150.0, "rapid": 50.0, "spindle": 80.0}
    wire.report(stat=5)  # running
    wire.clear()
    wire.report(stat=4)  # M2/M30: cm_reset_overrides
    assert wire.session.model.overrides == {"feed": 100.0, "rapid": 100.0, "spindle": 80.0}
    assert wire.lines() == []  # known from the firmware's rule: nothing asked


def test_an_override_in_an_alarm_is_refused_with_its_code() -> None:
    wire = ready(101.06)
    wire.report(stat=2)  # ALARM
    with pytest.raises(Rejected) as err:
        wire.session.override(feed=110)
    assert err.value.code == 204


@pytest.mark.parametrize(
    "state", [S.RUN, *(s for s in S if s.is_lockout), S.HOLD], ids=lambda s: s.name
)
def test_no_job_line_is_written_in_a_lockout_or_a_hold_even_before_its_drain(state: S) -> None:
    """The job's gate (`_job_lines_wait`, `_pump`'s and the express step's): while the
    model says ALARM, SHUTDOWN, PANIC or HOLD, an answer that frees the window writes
    no line of the job, whatever the drain that the state's report starts has done yet.
    In RUN the same answers write the next lines."""
    wire, stream = streaming(101.06)
    sent = stream.sent
    wire.session.model.state = state  # as a report has just set it
    for line in data_lines(wire):
        wire.answer(line)
    if state is S.RUN:
        assert stream.sent > sent and data_lines(wire)
    else:
        assert stream.sent == sent and not data_lines(wire)
