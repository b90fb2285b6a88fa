"""g2core's session by plain calls: every rule of the controller, without a port or a clock.

The same rules are tested end to end over ptys in tests/machine/; here each
is pinned at the level where it lives, thousands of steps a second.
"""

from __future__ import annotations

import json

import pytest

from hostd.protocol.commands import Realtime
from hostd.protocol.errors import Busy, ControllerError, NotConnected, Rejected
from hostd.protocol.g2builds import Build
from hostd.protocol.g2handshake import BANNER_WAIT
from hostd.protocol.g2kills import FLUSH_CONFIRM_TIMEOUT
from hostd.protocol.messages import Response
from hostd.protocol.states import MachineState as S
from hostd.protocol.stream import Stream
from hostd.protocol.vocabulary import (
    Closing,
    Detected,
    Excepted,
    Lane,
    Phase,
    Probed,
    Ready,
    Reported,
    StreamEnd,
    StreamEnded,
)
from tests.protocol.g2wire import BANNER, BUILDS, JOB_KILLERS, Wire


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    """Every rule runs on every build (tests/protocol/g2wire.py BUILDS), unless a test
    names the builds it applies to (hostd/protocol/g2builds.py)."""
    named = any(
        m.name == "parametrize" and "fb" in str(m.args[0])
        for m in metafunc.definition.iter_markers()
    )
    if "fb" in metafunc.fixturenames and not named:
        metafunc.parametrize("fb", BUILDS)


def job(*lines: str) -> Stream:
    return Stream(job_id=1).feed_all(enumerate(lines, start=1))


def moves(n: int) -> Stream:
    return job(*(f"G1 X{i % 100} F1000" for i in range(n)))


def ready(**options: object) -> Wire:
    wire = Wire(**options)  # type: ignore[arg-type]
    wire.connect()
    return wire


# -- the handshake -------------------------------------------------------------


def test_nothing_is_written_before_the_banner_then_settings_one_at_a_time(fb: float) -> None:
    wire = Wire(fb)
    wire.session.open()
    assert wire.pump() == []
    wire.feed(BANNER)
    first = wire.lines()
    assert first == [b'{"spc":null}\n']  # which spindle keys the board has, first
    wire.answer(first[0], {"spc": 0})
    assert wire.lines()[-1] == b'{"ej":1}\n'  # the next setting waits for this answer
    wire.answer(wire.lines()[-1])
    assert wire.lines()[-1] == b'{"jv":4}\n'


def test_the_handshake_ends_ready_after_settings_home_and_a_report(fb: float) -> None:
    wire = Wire(fb, status_interval=0.1, signal_keys=["in1"])
    wire.session.open()
    wire.feed(BANNER)
    while not wire.session.ready:
        wire.answer(wire.unanswered[0])
    sent = [json.loads(x) for x in wire.lines()]
    # ... with the overrides in force asked before the last report (BANNER's build: fro..)
    names = ["spc", "ej", "jv", "sv", "qv", "si", "sr", "fro", "home", "sr"]
    assert [next(iter(x)) for x in sent] == names
    assert sent[5] == {"si": 100}
    assert sent[6]["sr"]["in1"] is True and sent[6]["sr"]["mpox"] is True
    assert wire.of(Ready) == [Ready()]
    assert wire.session.model.homed is True and wire.session.model.state is S.READY


def test_a_board_that_prints_no_banner_is_asked_its_version(fb: float) -> None:
    wire = Wire(fb)
    wire.session.open()
    assert wire.session.next_deadline() == BANNER_WAIT
    assert wire.at(BANNER_WAIT) == [(Lane.CONTROL, b'{"fv":null,"fb":null}\n')]
    wire.answer(wire.unanswered[0], {"fv": 1.0, "fb": 101.06})
    assert wire.lines()[-1] == b'{"spc":null}\n'


def test_after_a_reset_only_the_banner_will_do(fb: float) -> None:
    wire = Wire(fb, handshake_timeout=5.0)
    wire.session.open(rebooting=True)
    assert wire.at(BANNER_WAIT) == []
    wire.at(5.0)
    assert wire.of(Closing) == [Closing("no SYSTEM READY banner from the controller within 5 s")]


@pytest.mark.parametrize(
    ("fb", "why"), [(440.2, "TinyG"), (99.5, "older than 100"), (None, "did not say")]
)
def test_firmware_that_is_not_g2core_100_or_later_is_refused(fb: float | None, why: str) -> None:
    wire = Wire()
    wire.session.open()
    wire.at(BANNER_WAIT)
    wire.answer(wire.unanswered[0], {"fv": 1.0, "fb": fb})
    (closing,) = wire.of(Closing)
    assert why in closing.reason
    assert not wire.session.ready


def test_a_refused_setting_fails_the_handshake_with_its_status(fb: float) -> None:
    wire = Wire(fb)
    wire.session.open()
    wire.feed(BANNER)
    wire.answer(wire.unanswered[0], {"spc": 0})
    wire.answer(wire.unanswered[0], {}, status=100)
    (closing,) = wire.of(Closing)
    assert "controller refused {'ej': 1}: 100" in closing.reason


def test_settings_refused_in_alarm_are_sent_again_once_it_is_cleared(fb: float) -> None:
    wire = Wire(fb)
    wire.session.open()
    wire.feed(BANNER)
    while not wire.session.ready:
        line = wire.unanswered[0]
        if line.startswith(b'{"ej"'):
            wire.answer(line, {}, status=204)
        else:
            wire.answer(line, None if b"sr" not in line else {"sr": {"stat": 2}})
    assert wire.session.model.state is S.ALARM
    wire.clear()
    wire.report(stat=1)
    assert [next(iter(json.loads(x))) for x in wire.lines()] == ["ej", "jv", "sv", "qv", "si", "sr"]
    assert {"spc", "sps"} <= json.loads(wire.lines()[-1])["sr"].keys()  # the board's, kept


# -- flow control --------------------------------------------------------------


def test_a_job_never_has_more_than_the_window_unanswered(fb: float) -> None:
    wire = ready(fb=fb, window=4)
    stream = moves(2_000)
    wire.session.start_stream(stream)
    most = 0
    while not stream.done:
        wire.pump()
        data = [x for x in wire.unanswered if not x.startswith(b"{")]
        most = max(most, len(data))
        if not wire.answer_all():
            wire.report(stat=4)  # the board rests
    assert most == 4
    assert stream.result.end is StreamEnd.COMPLETED
    assert (stream.sent, stream.acked) == (2_000, 2_000)


def test_queries_take_the_control_lane_not_the_jobs_window(fb: float) -> None:
    wire = ready(fb=fb, window=4)
    wire.session.start_stream(moves(100))
    tokens = [object() for _ in range(10)]
    for token in tokens:
        wire.session.send("?", token)
    wire.pump()
    control = [x for x in wire.unanswered if x.startswith(b"{")]
    data = [x for x in wire.unanswered if not x.startswith(b"{")]
    assert len(data) == 4 and len(control) == 4  # the lane is four deep; the rest wait
    assert control[0] == b'{"sr":null}\n'
    wire.answer_all(data=False)
    wire.answer_all(data=False)
    wire.answer_all(data=False)
    assert all(wire.settled(t) for t in tokens)


def test_an_answer_is_matched_by_its_count_when_both_kinds_wait(fb: float) -> None:
    wire = ready(fb=fb)
    a, b = object(), object()
    wire.session.send("G0 X1", a)
    wire.session.send("{xvm:n}", b)
    wire.pump()
    wire.answer(b'{"xvm":null}\n', {"xvm": 6000})  # the board runs the {-line first
    settled = wire.settled(b)
    assert settled is not None and isinstance(settled.outcome, Response)
    assert settled.outcome.body == {"xvm": 6000}
    assert wire.settled(a) is None


def test_an_answer_to_no_line_is_a_lexical_fault_and_books_nothing(fb: float) -> None:
    wire = ready(fb=fb)
    wire.feed('{"r":{},"f":[1,0,9]}')
    (fault,) = wire.of(Detected)
    assert fault.fault == "lexical"


def test_a_short_count_answer_is_a_report_not_an_answer(fb: float) -> None:
    wire = ready(fb=fb)
    token = object()
    wire.session.send("G28.2 X0", token)
    wire.pump()
    wire.feed('{"r":{"msg":"Homing error - Switches misconfigured"},"f":[1,240,1]}')
    assert wire.settled(token) is None  # cycle_homing.cpp's extra answer is not booked
    (report,) = wire.of(Excepted)
    assert report.fields["st"] == 240
    wire.answer(b"G28.2 X0\n", {}, status=240)
    settled = wire.settled(token)
    assert settled is not None and isinstance(settled.outcome, Response)
    assert settled.outcome.status == 240


def test_an_answer_too_long_fails_the_control_line_being_run(fb: float) -> None:
    wire = ready(fb=fb)
    token = object()
    wire.session.send("{sys:n}", token)
    wire.pump()
    wire.feed('{"er":{"fb":101.06,"st":113,"msg":"JSON output too long"}}')
    settled = wire.settled(token)
    assert settled is not None and isinstance(settled.outcome, ControllerError)
    assert settled.outcome.status == 113


# -- holds ---------------------------------------------------------------------


def test_a_paused_job_writes_nothing_until_resumed(fb: float) -> None:
    wire = ready(fb=fb, window=4)
    stream = moves(50)
    wire.session.start_stream(stream)
    wire.pump()
    wire.session.pause_stream()
    assert wire.pump() == [(Lane.REALTIME, b"!\n")]
    wire.answer_all()  # the window empties while the board enters its hold...
    wire.report(stat=6)
    assert len(wire.lines(Lane.DATA)) == 4  # ...and nothing more of the job is written
    wire.session.resume_stream()
    wire.report(stat=5)
    assert wire.lines(Lane.REALTIME)[-1] == b"~\n"
    assert len(wire.lines(Lane.DATA)) == 8


@pytest.mark.parametrize("fb", JOB_KILLERS)  # gc2 and ^D's flush: 101.02+
def test_a_line_sent_in_a_hold_runs_inside_it_at_once(fb: float) -> None:
    wire = ready(fb=fb)
    wire.report(stat=6)
    token = object()
    wire.session.send("M5", token)
    assert wire.pump() == [(Lane.CONTROL, b'{"gc2":"M5"}\n')]
    with pytest.raises(Busy, match="send settings as JSON"):
        wire.session.send("$xvm=1000", object())


def test_no_line_written_after_the_resume_carries_the_hold() -> None:
    """Issue 24 part 5: the `~` ends in-hold admission in the same step."""
    wire = ready(window=4)
    wire.session.start_stream(moves(50))
    wire.pump()
    wire.session.pause_stream()
    wire.answer_all()
    wire.report(stat=6)
    wire.clear()
    tokens = [object() for _ in range(6)]
    for i, token in enumerate(tokens):  # more than the control lane holds: some wait
        wire.session.send(f"G0 Z{i + 1}", token)
    wire.session.resume_stream()  # in the same step as the sends: nothing written yet
    wire.pump()
    written = wire.lines()
    cycle_start = written.index(b"~\n")
    assert not any(b"gc2" in line for line in written[cycle_start:])
    assert any(b"gc2" in line for line in written[:cycle_start])
    sent = b"".join(written)
    waited = [t for i, t in enumerate(tokens) if b'"G0 Z%d"' % (i + 1) not in sent]
    assert waited  # the lane was full: these were still on the host at the `~`
    for token in waited:
        settled = wire.settled(token)
        assert settled is not None and isinstance(settled.outcome, Busy)
        assert "the hold ended" in settled.outcome.message
    # The board has not reported the end of the hold yet; a line sent now is not run in it.
    with pytest.raises(Busy):
        wire.session.send("G0 Z9", object())
    wire.pump()
    assert not any(b"Z9" in line for line in wire.lines())


def test_a_hold_after_a_resume_takes_in_hold_lines_again() -> None:
    wire = ready()
    wire.report(stat=6)
    wire.session.realtime(Realtime.CYCLE_START)
    wire.pump()
    token = object()
    wire.session.send("G0 X1", token)  # the hold is ending: a free line, after the `~`
    assert wire.pump() == [(Lane.DATA, b"G0 X1\n")]
    wire.report(stat=5)
    wire.report(stat=3)
    wire.session.realtime(Realtime.FEEDHOLD)
    wire.report(stat=6)
    wire.session.send("M5", object())
    assert (Lane.CONTROL, b'{"gc2":"M5"}\n') in wire.pump()


def test_a_free_line_still_waiting_when_a_hold_begins_is_not_sent(fb: float) -> None:
    wire = ready(fb=fb, window=1)
    first, second = object(), object()
    wire.session.send("G0 X1", first)
    wire.session.send("G0 X2", second)
    wire.pump()
    wire.report(stat=6)  # the hold begins with X2 still on the host
    settled = wire.settled(second)
    assert settled is not None and isinstance(settled.outcome, Busy)
    assert "a hold began" in settled.outcome.message
    wire.answer_all()
    assert b"G0 X2\n" not in wire.lines()


def test_client_actions_are_busy_during_an_operation_but_its_own_lines_pass(
    fb: float,
) -> None:
    wire = ready(fb=fb)
    wire.session.set_operation(True)
    with pytest.raises(Busy, match="running an operation"):
        wire.session.send("G0 X1", object())
    wire.session.send("G90", object(), operation=True)
    assert wire.pump() == [(Lane.DATA, b"G90\n")]


# -- lockouts, clears, flushes -------------------------------------------------


def test_an_alarm_drains_the_job_and_refuses_actions_until_cleared(fb: float) -> None:
    wire = ready(fb=fb)
    stream = moves(50)
    wire.session.start_stream(stream)
    wire.pump()
    wire.feed('{"er":{"fb":101.06,"st":203,"msg":"Limit switch hit"}}')
    assert stream.result.end is StreamEnd.FAILED
    assert stream.result.code == 204
    with pytest.raises(Rejected) as refused:
        wire.session.send("G0 X1", object())
    assert refused.value.code == 204 and "Limit switch hit" in refused.value.message
    query = object()
    wire.session.send("{pos:n}", query)  # queries still go
    wire.pump()
    assert b'{"pos":null}\n' in wire.lines(Lane.CONTROL)


def test_a_clear_waits_until_no_data_line_is_unanswered(fb: float) -> None:
    wire = ready(fb=fb)
    wire.session.send("G0 X1", object())
    wire.pump()
    wire.feed('{"er":{"fb":101.06,"st":203,"msg":"Limit switch hit"}}')
    wire.report(stat=2)
    token = object()
    assert wire.session.clear(token)
    wire.pump()
    assert b'{"clear":null}\n' not in wire.lines()  # G0 X1 could still run after it
    if Build(fb).alarm_is_state:
        wire.answer(b"G0 X1\n", {}, status=204)
    else:  # a board that never alarms was killed by hostd: the kill dropped G0 X1
        wire.feed('{"er":{"fb":101.03,"st":207,"msg":"Kill job - Job killed by ^d"}}')
        wire.answer(b"$stat\n", {"stat": 4})  # the kill's fence, read after it
    wire.pump()
    assert wire.lines()[-1] == b'{"clear":null}\n'


def test_panic_is_left_only_by_a_reset(fb: float) -> None:
    wire = ready(fb=fb)
    wire.feed('{"er":{"fb":101.06,"st":20,"msg":"Internal error"}}')  # raises PANIC
    with pytest.raises(Rejected, match="only by a reset"):
        wire.session.clear(object())
    wire.session.reset()
    assert wire.pump()[-1] == (Lane.REALTIME, b"\x18\n")


@pytest.mark.parametrize("fb", JOB_KILLERS)  # gc2 and ^D's flush: 101.02+
def test_after_a_job_kill_no_data_line_goes_until_the_board_shows_the_flush(
    fb: float,
) -> None:
    wire = ready(fb=fb)
    stream = moves(50)
    wire.session.start_stream(stream)
    wire.pump()
    wire.session.realtime(Realtime.JOB_KILL)
    wire.pump()
    assert stream.result.end is StreamEnd.CANCELLED
    token = object()
    wire.session.send("{xvm:n}", token)  # queries still run meanwhile
    wire.session.set_operation(False)
    wire.pump()
    assert wire.settled(token) is None and b'{"xvm":null}\n' in wire.lines()
    wire.report(stat=4)  # a stop is no proof of a kill
    assert stream.discarded == 0 and wire.session.flushing()
    wire.feed('{"er":{"fb":101.06,"st":207,"msg":"Kill job - Job killed by ^d"}}')
    assert stream.discarded == 0 and wire.session.flushing()  # nor is its er 207 alone
    wire.answer(b"$stat\n", {"stat": 4})  # the fence behind the ^D: read after it
    assert stream.discarded == 4  # the four lines in flight were discarded
    assert not wire.session.flushing()


def test_a_stop_read_before_the_flush_went_out_proves_nothing(fb: float) -> None:
    wire = ready(fb=fb)
    stream = moves(50)
    wire.session.start_stream(stream)
    wire.pump()
    # One batch: the board says it stopped, and the host decides a flush; the
    # stop was printed before the `%` reached the board.
    wire.session.realtime(Realtime.QUEUE_FLUSH)
    wire.session.receive(b'{"sr":{"stat":3}}')
    assert wire.session.flushing() and stream.discarded == 0
    wire.pump()  # the `%` goes out
    wire.report(stat=3)
    assert not wire.session.flushing() and stream.discarded == 4


def test_an_unconfirmed_flush_gives_up_after_its_timeout(fb: float) -> None:
    wire = ready(fb=fb)
    wire.session.realtime(Realtime.QUEUE_FLUSH)
    wire.pump()
    assert wire.session.flushing()
    wire.at(FLUSH_CONFIRM_TIMEOUT)
    assert not wire.session.flushing()


def test_an_exception_holds_actions_until_a_status_report(fb: float) -> None:
    wire = ready(fb=fb)
    wire.feed('{"er":{"fb":101.06,"st":107,"msg":"Input exceeds max length"}}')
    assert wire.lines() == [b'{"sr":null}\n']
    token = object()
    wire.session.send("G0 X1", token)
    assert wire.pump() == []
    wire.report(stat=1)
    assert wire.pump() == [] and wire.lines()[-1] == b"G0 X1\n"


# -- what the board tells ------------------------------------------------------


def test_reports_carry_the_snapshot_they_left(fb: float) -> None:
    wire = ready(fb=fb)
    wire.report(stat=5, posx=1.5)
    wire.report(stat=3)
    first, second = wire.of(Reported)
    assert first.snapshot["state"]["name"] == "RUN" and first.snapshot["position"]["x"] == 1.5
    assert second.snapshot["state"]["name"] == "PROGRAM_STOP"


def test_a_probe_result_is_kept_and_told(fb: float) -> None:
    wire = ready(fb=fb)
    wire.feed('{"prb":{"e":1,"x":1.5,"y":2.0,"z":-3.25}}')
    (probe,) = wire.of(Probed)
    assert probe.probe == {"ok": True, "position": {"x": 1.5, "y": 2.0, "z": -3.25}}
    assert wire.session.model.probe == probe.probe


def test_homed_is_asked_when_homing_ends(fb: float) -> None:
    wire = ready(fb=fb)
    wire.report(stat=9)
    wire.report(stat=1)
    assert wire.lines()[-1] == b'{"home":null}\n'


def test_a_banner_mid_session_closes_it(fb: float) -> None:
    wire = ready(fb=fb)
    wire.feed(BANNER)
    assert wire.of(Closing) == [Closing("controller restarted (unexpected SYSTEM READY)")]


def test_a_silent_board_is_asked_then_given_up(fb: float) -> None:
    wire = ready(fb=fb, heartbeat=2.0)
    assert wire.at(2.0) == [(Lane.CONTROL, b'{"sr":null}\n')]
    wire.at(3.9)
    assert wire.of(Closing) == []
    wire.at(4.0)
    (closing,) = wire.of(Closing)
    assert "silent for 4 s" in closing.reason


def test_closing_settles_every_request_and_interrupts_the_job(fb: float) -> None:
    wire = ready(fb=fb)
    stream = moves(50)
    wire.session.start_stream(stream)
    waiting, queued = object(), object()
    wire.session.send("{xvm:n}", waiting)
    wire.pump()
    wire.session.close("unplugged")
    wire.pump()
    settled = wire.settled(waiting)
    assert settled is not None and isinstance(settled.outcome, NotConnected)
    assert stream.result.end is StreamEnd.INTERRUPTED
    assert wire.session.phase is Phase.CLOSED
    with pytest.raises(NotConnected):
        wire.session.send("G0 X1", queued)


def test_a_long_job_streams_in_plain_calls(fb: float) -> None:
    """The session alone moves a 10,000-line job: no port, no event loop turn a line."""
    wire = ready(fb=fb, window=8)
    stream = moves(10_000)
    wire.session.start_stream(stream)
    while not stream.done:
        wire.pump()
        if not wire.answer_all():
            wire.report(stat=4)
    assert (stream.sent, stream.acked, stream.rejected) == (10_000, 10_000, 0)


def test_a_job_fed_a_few_lines_at_a_time_writes_only_what_it_was_fed(fb: float) -> None:
    """The caller owns the file: the session writes the lines it was given, says when it
    has room and nothing ahead (`starved`), and tells the end once, as an event."""
    wire = ready(fb=fb, window=4)
    stream = Stream(job_id=7)
    stream.feed(1, "G1 X1 F100")
    wire.session.start_stream(stream)
    wire.pump()
    assert wire.lines(Lane.DATA) == [b"G1 X1 F100\n"]
    assert stream.starved and stream.wanted() > 0  # room for three more, none fed
    for number in (2, 3, 4, 5, 6):
        stream.feed(number, f"G1 X{number}")
    wire.pump()
    assert len(wire.lines(Lane.DATA)) == 4 and not stream.starved  # the window, no more
    wire.answer_all()  # each answer frees a slot: lines 5 and 6 follow, and are answered
    wire.report(stat=4)
    assert (stream.sent, stream.acked) == (6, 6)
    assert not wire.of(StreamEnded)  # all answered, the board at rest, but the file goes on
    stream.end_of_input()
    wire.pump()
    wire.answer_all()  # the status query that finds the board at rest
    assert wire.of(StreamEnded) == [StreamEnded(7, stream.result)]
    assert stream.result is not None and stream.result.end is StreamEnd.COMPLETED
    wire.report(stat=4)
    assert len(wire.of(StreamEnded)) == 1  # told once


def test_a_line_never_to_send_fails_the_job_when_its_turn_comes(fb: float) -> None:
    wire = ready(fb=fb, window=4)
    stream = job("G1 X1 F100", "G1 X2 " + "X" * 600, "G1 X3")
    wire.session.start_stream(stream)
    wire.pump()
    assert wire.lines(Lane.DATA) == [b"G1 X1 F100\n"]  # the line before it still goes
    (ended,) = wire.of(StreamEnded)
    assert ended.result.end is StreamEnd.FAILED and ended.result.code == -32602
    assert ended.result.message is not None and ended.result.message.startswith("line 2:")
    assert stream.sent == 1


@pytest.mark.parametrize("fb", BUILDS)
def test_a_json_line_in_a_job_waits_for_the_lines_before_it(fb: float) -> None:
    """The board reads a `{`-line ahead of data lines still waiting (xio.cpp:789): written
    beside them it would run first, so it goes only once the lines before it are answered."""
    wire = ready(fb=fb, window=4)
    stream = job("G1 X1 F100", '{"out4":1}', "G1 X2")
    wire.session.start_stream(stream)
    wire.pump()
    assert wire.lines() == [b"G1 X1 F100\n"]  # not the `{`-line, nor what follows it
    wire.answer(b"G1 X1 F100\n", {})
    # Lines after it may follow at once: the board reads it ahead of them anyway.
    assert wire.lines()[-2:] == [b'{"out4":1}\n', b"G1 X2\n"]
    wire.answer(b'{"out4":1}\n', {"out4": 1})
    wire.answer(b"G1 X2\n", {})
    wire.report(stat=4)
    assert stream.result.end is StreamEnd.COMPLETED and stream.acked == 3


def test_the_executing_line_is_read_only_from_reports_that_show_motion(fb: float) -> None:
    """canonical_machine.cpp: `line` is the runtime's N while moving, the last line *read*
    once stopped or holding: only a RUN report says which line executes."""
    wire = ready(fb=fb, window=4)
    stream = Stream(job_id=1, encode=wire.session.encode_job_line, numbered=True)
    stream.feed_all(enumerate((f"G1 X{i} F100" for i in range(10)), start=1))
    wire.session.start_stream(stream)
    wire.pump()
    assert wire.lines(Lane.DATA)[0].startswith(b"N1 ")  # numbered with the file line
    wire.report(stat=5, line=2, vel=100)
    assert stream.line_executed == 2
    wire.report(stat=6, line=4)  # a hold: the line read ahead, not the one running
    assert stream.line_executed == 2
    wire.report(stat=5, line=9, vel=100)  # never sent: a stale or foreign number
    assert stream.line_executed == 2
    wire.report(stat=5, line=3)  # filtered: `vel` left out, still the 100 last reported
    assert stream.line_executed == 3
    wire.report(stat=5, line=1)  # never backwards
    assert stream.line_executed == 3


def test_a_run_report_before_the_first_block_moves_says_no_line_executes(fb: float) -> None:
    """stat is RUN from the first move *parsed* (cm_cycle_start), but `line` is the
    parser's until a block executes (ACTIVE_MODEL, MOTION_STOP; `vel` 0 until then):
    the planner's startup reports the last line read. Taken, a job lost there was
    planned to resume at that line, past every line the board had not run."""
    wire = ready(fb=fb, window=4)
    stream = Stream(job_id=1, encode=wire.session.encode_job_line, numbered=True)
    stream.feed_all(enumerate((f"G1 X{i} F100" for i in range(10)), start=1))
    wire.session.start_stream(stream)
    wire.pump()
    for line in (b"N1 G1 X0 F100\n", b"N2 G1 X1 F100\n", b"N3 G1 X2 F100\n"):
        wire.answer(line, {})
    wire.report(stat=5, line=4, vel=0)  # the planner fills; nothing moves yet
    assert stream.line_executed is None
    wire.report(stat=5, line=1, vel=40)  # the first block runs: the runtime's line
    assert stream.line_executed == 1


def test_a_filtered_report_leaves_out_what_the_last_automatic_one_said(fb: float) -> None:
    """report.cpp: a filtered report leaves out what did not change since the last
    *automatic* report (:480); an answer to `{"sr":null}` leaves that record alone (:385).
    An answer in the planner's startup says the parser's line (8); the automatic report
    in motion leaves out the runtime's line, 1 as the automatic one before the answer
    said: line 1 executes, not the 8 a merged model would still hold."""
    wire = ready(fb=fb, window=4)
    stream = Stream(job_id=1, encode=wire.session.encode_job_line, numbered=True)
    stream.feed_all(enumerate((f"G1 X{i} F100" for i in range(10)), start=1))
    wire.session.start_stream(stream)
    wire.pump()
    for i in range(4):
        wire.answer(f"N{i + 1} G1 X{i} F100\n".encode(), {})
    wire.report(stat=5, line=1)  # the cycle starts as N1 is parsed; nothing moves
    wire.session.send("?", object())
    wire.pump()
    wire.answer(b'{"sr":null}\n', {"sr": {"stat": 5, "line": 8, "vel": 0}})
    assert stream.line_executed is None
    wire.report(vel=40)  # N1 moves: `line` is 1 still, as last reported automatically
    assert stream.line_executed == 1


def test_the_lockout_says_what_caused_it_and_what_ends_it() -> None:
    wire = ready()
    assert wire.session.lockout() is None
    wire.feed('{"er":{"fb":101.06,"st":20,"msg":"Internal error"}}')  # raises PANIC
    assert wire.session.lockout() == {
        "state": "PANIC",
        "message": "Internal error",
        "clear": "machine.reset",
    }
