"""g2core's safety gates that a mutation campaign found no test guarding, byte by byte.

Each test pins one rule of the session's layers (g2kills.py, g2lockouts.py,
g2connection.py, g2books.py; docs/protocol.md, "Answers that answer no line", "A kill's
fence", "Firmware builds") by what is written, refused or told, and was checked to fail
with the guard it names (its docstring's last line) removed or changed:

- a fault's stop of a job is `!` then `%`, and the job's lines in flight are
  accounted only once the board shows its stop;
- a `%` after a ^D waits for its own proof, a stop, not for the kill's fence;
- a report of READY after a `%` proves no flush: the line the board still runs is
  answered as run, not told discarded;
- a client's line a kill threw away is settled with the kill's code, 207, and one a
  `%` threw away as a queue flush's, not as a kill's;
- before 101.02, once hostd's own ALARM (its ^D) is cleared, a later alarm's 204s
  count rejected, not discarded;
- before 101.02 an M30 answered OK just before hostd's ^D took effect does not stop
  hostd from clearing the ALARM its ^D makes;
- a 205 answer alone shows SHUTDOWN, not ALARM;
- before 101.02 hostd's own ALARM (its ^D) is told as an exception, and a line
  refused in it names the kill, not an older exception;
- a 206 answer shows PANIC at once, over an ALARM: the next clear is refused;
- a PANIC is the board's own at once on every build: hostd writes no ^D of its own;
- a board silent since its last line is asked for a report a heartbeat later: the
  session names that time as its next deadline, with no other armed;
- a new connection keeps nothing of a kill or an alarm the old one left unfinished:
  a clear asked in a later alarm's hold still waits for that alarm's own kill, and
  a clear of an ALARM the board shows goes, and a lockout hostd kept is not kept
  over a board that reports itself free;
- a session once ready is not given up when the handshake's timeout passes;
- a board booting after a reset is written nothing until its banner, however long it
  takes within the handshake's timeout (no heartbeat query before the session is ready);
- a session halted by an internal fault writes nothing of its own either (a
  heartbeat query, an override) until machine.reset;
- a status query asked while the link is down writes nothing, then or before the
  next connection's banner;
- a heartbeat query whose answer was lost, while the board answered the line after
  it, does not make the board a silent one;
- machine.reset with the link down is refused, and no 0x18 is kept to reset the
  board when the link comes back;
- a client's line still waiting to be written when the link drops is told so at once,
  and nothing the old connection had still to write goes out on the new one.
"""

from __future__ import annotations

import pytest

from hostd.protocol.commands import Realtime
from hostd.protocol.errors import ControllerError, NotConnected, Rejected
from hostd.protocol.messages import Response
from hostd.protocol.states import MachineState as S
from hostd.protocol.vocabulary import Closing, Excepted, Lane, StreamEnd
from tests.protocol.g2wire import BUILDS, JOB_KILLERS, Wire
from tests.protocol.test_g2core_builds import CLEAR, LIMIT, data_lines, kill_report, streaming
from tests.protocol.test_g2core_kill_fences import FENCE, ready
from tests.protocol.test_g2core_write_gates import moves

KILL_REPORT = '{"er":{"fb":%s,"st":207,"msg":"Kill job - Job killed by ^d"}}'


def move_then(fb: float, command: Realtime) -> tuple[Wire, object]:
    """A ready board, a client's `G0 X1` written to it, then `command`; and the token the
    client's answer is settled with."""
    wire = ready(fb)
    token = object()
    wire.session.send("G0 X1", token)
    wire.pump()
    wire.session.realtime(command)
    wire.pump()
    return wire, token


def state(wire: Wire) -> S | None:
    """The state the session shows now (read afresh: each call may follow a change)."""
    return wire.session.model.state


@pytest.mark.parametrize("fb", BUILDS)
def test_a_faults_stop_of_a_job_holds_then_flushes_the_board(fb: float) -> None:
    """A fault met mid-job (a door opened, an e-stop input) fails the job and stops the
    board: `!` and then `%`. A `!` alone leaves the job's moves in the planner, and the
    operator's next `~` would run the rest of a job already told failed. Its lines in
    flight are counted discarded once a stop read after the `%` shows the flush, and no
    data line goes before then.

    Guards: g2kills.py `_stop_board`, its `%`.
    """
    wire = ready(fb)
    stream = moves(50)
    wire.session.start_stream(stream)
    wire.pump()
    wire.session.stop_stream(1008, "fault active: door")
    wire.pump()
    assert stream.result is not None and stream.result.end is StreamEnd.FAILED
    assert wire.lines(Lane.REALTIME) == [b"!\n", b"%\n"]
    wire.session.send("G0 X1", object())
    wire.pump()
    assert b"G0 X1\n" not in wire.lines()
    assert stream.discarded == 0
    wire.report(stat=3)  # the `%` ran: the planner and the lines it held are gone
    assert stream.discarded == 4
    assert wire.lines()[-1] == b"G0 X1\n"


@pytest.mark.parametrize("fb", JOB_KILLERS)
def test_a_flush_after_a_kill_waits_for_its_own_stop_not_the_kills_fence(fb: float) -> None:
    """A cancel (^D) and then a `%`: the kill's fence answered shows the kill, not the
    flush. No data line goes until a stop read after the `%` shows it; the kill's own
    report at program end (stat 4, `_run_job_kill` ends in `cm_program_end`,
    cycle_feedhold.cpp) is such a stop.

    Guards: g2kills.py `_kill_fenced` (it ends a kill's wait only) and `_FLUSH_CONFIRMED` (stat 4).
    """
    wire = ready(fb)
    wire.session.realtime(Realtime.JOB_KILL)
    wire.session.realtime(Realtime.QUEUE_FLUSH)
    wire.pump()
    wire.feed(KILL_REPORT % fb)
    wire.answer(FENCE, {"stat": 4})  # the kill ran and its fence was read
    wire.session.send("G0 X1", object())
    wire.pump()
    assert wire.session.flushing()
    assert b"G0 X1\n" not in wire.lines()
    wire.report(stat=4)
    assert not wire.session.flushing()
    assert wire.lines()[-1] == b"G0 X1\n"


@pytest.mark.parametrize("fb", BUILDS)
def test_a_ready_report_after_a_flush_proves_nothing_and_the_line_still_runs(
    fb: float,
) -> None:
    """A `%` at rest flushes nothing (cycle_feedhold.cpp: "Queue flush is not honored
    except during a feedhold"); only a stop (stat 3 or 4) shows a flush. A fresh board
    reports READY (stat 1) until it first runs something: that report says nothing of
    the `%`. The move written before it is still read and run, and its client is told
    it ran, not that the flush discarded it.

    Guards: g2kills.py `_FLUSH_CONFIRMED` (stat 3 and 4 only).
    """
    wire, token = move_then(fb, Realtime.QUEUE_FLUSH)
    wire.report(stat=1)
    assert wire.session.flushing()
    assert wire.settled(token) is None
    wire.answer(b"G0 X1\n", {})
    settled = wire.settled(token)
    assert settled is not None and isinstance(settled.outcome, Response)
    assert settled.outcome.ok


@pytest.mark.parametrize("fb", JOB_KILLERS)
def test_a_line_a_kill_threw_away_is_settled_with_the_kills_code(fb: float) -> None:
    """The client whose move a ^D threw away unread is told so with g2core's code for a
    job kill, 207 (STAT_KILL_JOB): not 3 (a no-op, the code of a `%`'s discards), which
    would read as a flush the operator never asked for.

    Guards: g2kills.py `_discarded` (207 for a kill).
    """
    wire, token = move_then(fb, Realtime.JOB_KILL)
    wire.answer(FENCE, {"stat": 4})  # read after the ^D: G0 X1 is gone
    settled = wire.settled(token)
    assert settled is not None and isinstance(settled.outcome, ControllerError)
    assert settled.outcome.status == 207
    assert "job kill" in str(settled.outcome)


@pytest.mark.parametrize("fb", BUILDS)
def test_a_line_a_flush_threw_away_is_settled_as_the_flushs_not_a_kills(fb: float) -> None:
    """The client whose move a `%` threw away is told it was the queue flush, as the
    operator asked: not a job kill (207), which would say the job was cancelled.

    Guards: g2kills.py `_confirm_flush` (settled with the `%`'s own reason).
    """
    wire, token = move_then(fb, Realtime.QUEUE_FLUSH)
    wire.report(stat=3)
    settled = wire.settled(token)
    assert settled is not None and isinstance(settled.outcome, ControllerError)
    assert settled.outcome.status != 207
    assert "queue flush" in str(settled.outcome)


def test_101_03_a_panic_is_the_boards_own_and_hostd_writes_no_kill() -> None:
    """On 101.02-101.04 an alarm never becomes ALARM on the board, so hostd stops it with
    a ^D. A PANIC does: `cm_panic` halts the motors and sets PANIC before it reports
    (101.03 alarm.cpp:226-243). hostd writes nothing for it, no ^D and no fence: only the
    query for a report.

    Guards: g2lockouts.py `_announced` (`lockout is not MachineState.PANIC`).
    """
    wire = ready(101.03)
    wire.feed('{"er":{"fb":101.03,"st":20,"msg":"Internal error"}}')
    assert state(wire) is S.PANIC
    assert wire.lines() == [b'{"sr":null}\n']


def test_100_26_after_a_cancels_alarm_is_cleared_a_later_alarms_refusals_count_rejected() -> None:
    """Before 101.02 hostd's ^D is an ALARM whose 204s count the lines it caught as
    discarded; its clear ends that. The next job's limit alarm is the board's, not
    hostd's: the lines it refuses were taken and refused, and the job counts them
    rejected (a discarded line reads as one hostd chose to throw away).

    Guards: g2lockouts.py `_cleared` (`_kill_alarm = False`).
    """
    wire, first = streaming(100.26)
    caught = data_lines(wire)
    wire.session.realtime(Realtime.JOB_KILL)
    wire.pump()
    wire.feed(kill_report(100.26))
    for line in caught:
        wire.answer(line, {}, status=204)
    assert first.discarded == len(caught)
    wire.answer(CLEAR, {"clear": None})
    wire.answer_all()
    wire.report(stat=3)
    assert state(wire) is S.PROGRAM_STOP
    second = moves(20)
    wire.session.start_stream(second)
    wire.pump()
    held = data_lines(wire)
    wire.feed(LIMIT % 100.26)
    for line in held:
        wire.answer(line, {}, status=204)
    assert second.rejected == len(held) and second.discarded == 0


@pytest.mark.parametrize("fb", [100.26, 101.06])  # the builds that report ALARM (stat 2)
def test_a_206_answer_in_an_alarm_shows_panic_and_the_next_clear_is_refused(fb: float) -> None:
    """A board that answers 206 is in PANIC, whatever the last report said (its own
    report of the PANIC may have been lost on the wire). The operator who cleared an
    ALARM and got 206 is shown PANIC, which only a reset leaves, and is not offered
    another clear as if an ALARM stood.

    Guards: g2lockouts.py `_refused_in_lockout` (PANIC over another lockout) and
    `_LOCKOUT_REJECTIONS` (206).
    """
    wire = ready(fb)
    wire.report(stat=2)
    assert state(wire) is S.ALARM
    token = object()
    assert wire.session.clear(token)
    wire.pump()
    wire.answer(CLEAR, {}, status=206)
    assert state(wire) is S.PANIC
    with pytest.raises(Rejected, match="only by a reset"):
        wire.session.clear(object())


@pytest.mark.parametrize("fb", [100.26, 101.06])  # the builds that enter SHUTDOWN
def test_a_205_answer_alone_shows_shutdown_and_refuses_with_its_code(fb: float) -> None:
    """A 205 answer says the board is in SHUTDOWN (an e-stop), before any report does.
    Shown as ALARM, the operator would be told 204 and read it as a limit: an M30 clears
    an ALARM on the board, but never a SHUTDOWN (alarm.cpp `cm_parse_clear`).

    Guards: g2lockouts.py `_LOCKOUT_OF` (205 is SHUTDOWN).
    """
    wire = ready(fb)
    wire.session.send("G0 X1", object())
    wire.pump()
    wire.answer(b"G0 X1\n", {}, status=205)
    assert state(wire) is S.SHUTDOWN
    with pytest.raises(Rejected) as refused:
        wire.session.send("G0 X2", object())
    assert refused.value.code == 205


def test_100_26_hostds_own_alarm_from_a_cancel_is_told_as_an_exception() -> None:
    """Before 101.02 hostd's ^D puts the board in ALARM ("EOT Received"). Clients are told
    that exception, as any other: a board shown in ALARM with no exception told would
    leave the operator no reason for it.

    Guards: g2lockouts.py `_on_kill_report` (its `Excepted`).
    """
    wire, _ = streaming(100.26)
    wire.session.realtime(Realtime.JOB_KILL)
    wire.pump()
    wire.feed(kill_report(100.26))
    assert state(wire) is S.ALARM
    told = wire.of(Excepted)
    assert [e.fields.get("st") for e in told] == [207]


@pytest.mark.parametrize("fb", BUILDS)
def test_a_silent_board_is_due_to_be_asked_one_heartbeat_after_its_last_line(
    fb: float,
) -> None:
    """The engine wakes the session only at the deadline it names. A board that stops
    printing (hung, its USB stalled) must be asked for a report one heartbeat after its
    last line, and given up a heartbeat later: with no deadline named the engine would
    sleep, and a dead board would be shown connected and at rest.

    Guards: g2connection.py `next_deadline` (the heartbeat's time).
    """
    wire = ready(fb)
    wire.now = 7.0
    wire.report(stat=3)  # the board's last line
    assert wire.session.next_deadline() == 7.0 + wire.session.heartbeat
    assert wire.at(7.0 + wire.session.heartbeat) == [(Lane.CONTROL, b'{"sr":null}\n')]


def reconnected(wire: Wire) -> None:
    """The link dropped and came back, the board not reset: a new handshake."""
    wire.session.close("link lost")
    wire.unanswered.clear()
    wire.connect()


@pytest.mark.parametrize("fb", [101.05, 101.06])
def test_a_kill_the_lost_link_left_unseen_does_not_let_a_later_alarms_clear_go_early(
    fb: float,
) -> None:
    """A cancel's ^D whose `er` 207 never arrived (the link dropped): the new connection
    owes no kill. A limit alarm then holds first and enters ALARM only with its own kill
    (cycle_feedhold.cpp `_run_alarm`); a clear written before that is answered OK and
    lost (alarm.cpp `cm_clear`), and the machine stays locked after the operator cleared
    it. The clear waits for the alarm's own 207.

    Guards: g2connection.py `close` (`_kills_unseen = 0`).
    """
    wire = ready(fb)
    wire.session.realtime(Realtime.JOB_KILL)
    wire.pump()
    reconnected(wire)
    wire.feed(LIMIT % fb)
    wire.answer_all()
    wire.report(stat=6, hold=4)  # the alarm's hold
    assert wire.session.clear(object())
    wire.pump()
    assert CLEAR not in wire.lines()
    wire.feed(KILL_REPORT % fb)  # the alarm's own kill: ALARM now
    wire.pump()
    assert CLEAR in wire.lines()


@pytest.mark.parametrize("fb", [101.05, 101.06])
def test_an_alarm_the_lost_link_left_in_its_hold_can_be_cleared_on_the_next_connection(
    fb: float,
) -> None:
    """A limit alarm read, and the link lost before the board's own kill was: the board
    went on into ALARM meanwhile. On the new connection its first report shows ALARM,
    and the operator's clear goes; kept waiting for a 207 printed on the old connection,
    it would never go and the machine could not be freed.

    Guards: g2connection.py `close` (`_alarm_kill_due = False`).
    """
    wire = ready(fb)
    wire.feed(LIMIT % fb)
    wire.answer_all()
    wire.session.close("link lost")
    wire.unanswered.clear()
    wire.connect({"stat": 2, "posx": 0, "posy": 0, "posz": 0, "unit": 1})
    assert state(wire) is S.ALARM
    assert wire.session.clear(object())
    wire.pump()
    assert CLEAR in wire.lines()


def test_101_03_the_lockout_hostd_kept_ends_with_the_connection() -> None:
    """On 101.03 the board never enters ALARM: after a limit hostd stops it (^D) and
    keeps a lockout of its own. A new connection starts from what the board says: its
    first report shows it stopped, and G-code is taken, not refused 204 for an ALARM
    that no board shows and no clear on the board can end.

    Guards: g2connection.py `close` (`_held = None`).
    """
    wire = ready(101.03)
    wire.feed(LIMIT % 101.03)
    assert state(wire) is S.ALARM
    reconnected(wire)
    assert state(wire) is S.READY
    wire.report(stat=3)
    assert state(wire) is S.PROGRAM_STOP
    wire.session.send("G0 X1", object())
    wire.pump()
    assert wire.lines()[-1] == b"G0 X1\n"


@pytest.mark.parametrize("fb", BUILDS)
def test_a_line_still_waiting_when_the_link_drops_is_told_at_once(fb: float) -> None:
    """A client's move waiting behind a flush's proof is never written once the link is
    gone: its asker is told the link was lost at once, not left to its own timeout.

    Guards: g2connection.py `close` (the outbox and the lane settled).
    """
    wire = ready(fb)
    wire.session.realtime(Realtime.QUEUE_FLUSH)
    wire.pump()
    token = object()
    wire.session.send("G0 X1", token)
    wire.pump()
    assert b"G0 X1\n" not in wire.lines()
    wire.session.close("link lost")
    wire.pump()
    settled = wire.settled(token)
    assert settled is not None and isinstance(settled.outcome, NotConnected)


@pytest.mark.parametrize("fb", JOB_KILLERS)
def test_nothing_the_lost_link_had_still_to_write_goes_on_the_next_one(fb: float) -> None:
    """A cancel decided in the step that found the link gone: its ^D and fence were never
    written. The next connection writes nothing before the board's banner (a stale
    `$stat` answered there is no line of the new connection's, and its books would be
    off by one from the first answer).

    Guards: g2connection.py `close` (`_out.clear()`).
    """
    wire = ready(fb)
    wire.session.realtime(Realtime.JOB_KILL)  # not yet handed to the engine
    wire.session.close("link lost")
    wire.unanswered.clear()
    wire.clear()
    wire.session.open()
    assert wire.pump() == []


@pytest.mark.parametrize("fb", BUILDS)
def test_a_board_booting_after_a_reset_is_written_nothing_until_its_banner(fb: float) -> None:
    """After 0x18 the board reboots, and only its banner says it is up. A boot longer
    than a heartbeat is no silent board: nothing is written to it meanwhile (no status
    query into a booting board), and if no banner comes the handshake's timeout says so.

    Guards: g2connection.py `tick` (no heartbeat before READY).
    """
    wire = Wire(fb, heartbeat=2.0, handshake_timeout=10.0)
    wire.session.open(rebooting=True)
    assert wire.at(3.0) == []
    assert wire.at(9.0) == []
    wire.at(10.0)
    assert wire.of(Closing) == [Closing("no SYSTEM READY banner from the controller within 10 s")]


@pytest.mark.parametrize("fb", BUILDS)
def test_a_halted_session_writes_nothing_of_its_own(fb: float) -> None:
    """An internal fault (hostd's books out of step) halts the session: nothing more is
    written until machine.reset, since hostd no longer knows what its lines would match.
    That holds for the session's own lines too: no heartbeat query to a silent board,
    and an override asked then sets nothing on the board.

    Guards: g2books.py `_book` (`if self.halted`).
    """
    wire = ready(fb)
    wire.session.halt("books out of step")
    wire.pump()
    wire.clear()
    wire.session.override(feed=50)
    wire.pump()
    wire.at(wire.session.heartbeat + 1.0)  # a silent board would be asked for a report
    assert wire.lines() == []


@pytest.mark.parametrize("fb", BUILDS)
def test_a_status_query_asked_while_the_link_is_down_writes_nothing(fb: float) -> None:
    """An operation waiting for the board to rest asks for a report now and then, the
    link lost or not (hostd/machine/rest.py `_polling`). Asked while the link is down,
    nothing is written, nor kept to be written when the next connection opens: before
    the banner nothing goes to the board, a rebooting one included.

    Guards: g2books.py `_ask_own` (nothing when CLOSED).
    """
    wire = ready(fb)
    wire.session.close("link lost")
    wire.unanswered.clear()
    wire.clear()
    wire.session.query_status()
    assert wire.pump() == []
    wire.session.open(rebooting=True)
    assert wire.pump() == []


@pytest.mark.parametrize("fb", BUILDS)
def test_a_heartbeat_whose_answer_was_lost_does_not_give_up_a_board_that_answers(
    fb: float,
) -> None:
    """The heartbeat's `{"sr":null}` answer lost on the wire (line noise), and the query
    written after it answered: the heartbeat was read (answers come in order), so the
    board lives. It is not given up a heartbeat later as silent, which would drop the
    link and interrupt what runs.

    Guards: g2books.py `_settle_unanswered` (a heartbeat given up was read).
    """
    wire = ready(fb)
    heartbeat = wire.session.heartbeat
    assert wire.at(heartbeat) == [(Lane.CONTROL, b'{"sr":null}\n')]
    wire.session.send("{xvm:n}", object())
    wire.pump()
    wire.unanswered.remove(b'{"sr":null}\n')  # its answer never arrives
    wire.answer(b'{"xvm":null}\n')
    wire.at(2 * heartbeat)
    assert wire.of(Closing) == []


def test_100_26_an_m30_answered_before_hostds_kill_does_not_keep_its_alarm() -> None:
    """Before 101.02 hostd's ^D is an ALARM that hostd clears itself. An M30 read just
    before the ^D and answered OK cleared nothing (there was no ALARM yet): hostd still
    clears its own ALARM once the 207 shows it, and the machine is not left locked by
    a cancel.

    Guards: g2core.py `_on_response` (`self._held and _clears(...)`).
    """
    wire = ready(100.26)
    wire.session.send("M30", object())
    wire.pump()
    wire.session.realtime(Realtime.JOB_KILL)
    wire.pump()
    wire.answer(b"M30\n", {})  # read before the ^D
    wire.feed(kill_report(100.26))
    assert state(wire) is S.ALARM
    wire.pump()
    assert CLEAR in wire.lines(Lane.DATA)


def test_100_26_a_line_refused_in_hostds_own_alarm_names_the_kill() -> None:
    """Before 101.02 hostd's ^D is an ALARM. G-code sent in it is refused 204 with the
    reason: the kill ("EOT Received"), not an exception read earlier (here a line too
    long), which would send the operator looking for a fault that is not there.

    Guards: g2lockouts.py `_on_kill_report` (`apply_exception` on 100.x).
    """
    wire = ready(100.26)
    wire.feed('{"er":{"fb":100.26,"st":107,"msg":"Input exceeds max length"}}')
    wire.report(stat=3)
    wire.session.realtime(Realtime.JOB_KILL)
    wire.pump()
    wire.feed(kill_report(100.26))
    with pytest.raises(Rejected) as refused:
        wire.session.send("G0 X1", object())
    assert refused.value.code == 204
    assert "EOT Received" in refused.value.message


@pytest.mark.parametrize("fb", BUILDS)
def test_a_reset_asked_with_the_link_down_is_refused_and_never_written(fb: float) -> None:
    """machine.reset (0x18) with the link down is refused as not connected. Kept and
    written once the link is back, it would reboot the board in the middle of the next
    handshake, or of whatever the operator started since.

    Guards: g2kills.py `reset` (`_require_open`).
    """
    wire = ready(fb)
    wire.session.close("link lost")
    wire.unanswered.clear()
    wire.clear()
    with pytest.raises(NotConnected):
        wire.session.reset()
    wire.session.open()
    assert wire.pump() == []


@pytest.mark.parametrize("fb", BUILDS)
def test_a_ready_session_outlives_the_handshakes_timeout(fb: float) -> None:
    """The handshake's timeout bounds the handshake only. A board that answered it and
    goes on answering is not dropped when that time comes: the link would close under a
    running job, seconds after every connect.

    Guards: g2connection.py `_own_answered` (the first report ends the handshake's deadline).
    """
    wire = Wire(fb, heartbeat=2.0, handshake_timeout=5.0)
    wire.connect()
    for now in (2.0, 4.0, 6.0):  # the heartbeat asked and answered, past the 5 s
        wire.at(now)
        wire.answer_all()
    assert wire.of(Closing) == []
    assert wire.session.ready
