"""The gates of a grbl handshake: what is asked, when, and what the operator is told.

Each test pins a rule of the handshake with a board found busy, refusing a
line, printing answers of before this link, or reset while connecting
(docs/dialects.md, "A board busy at connect"), by what the board is sent,
whether the link becomes ready, and what the operator reads: the same sans-I/O
session as tests/protocol/test_grbl_busy_at_connect.py, driven by hand.
"""

from __future__ import annotations

import pytest

from hostd.protocol.grbl.connection import BANNER_WAIT
from hostd.protocol.vocabulary import Closing, Detected, Excepted, Ready
from tests.protocol.test_grbl_busy_at_connect import (
    BANNER,
    HOLD,
    RUN,
    finish_handshake,
    occupied,
)
from tests.protocol.test_grbl_session import IDLE, Grbl

VER = ("[VER:1.1h.20190830:]", "[OPT:V,15,128]", "ok")
MODES = ("[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]", "ok")


def closed(grbl: Grbl) -> list[Closing]:
    return [e for e in grbl.events if isinstance(e, Closing)]


def told(grbl: Grbl) -> list[str]:
    return [str(e.fields.get("msg")) for e in grbl.events if isinstance(e, Excepted)]


@pytest.mark.parametrize(
    "report",
    [
        "<Alarm|MPos:0.000,0.000,0.000|FS:0,0>",
        "<Check|MPos:0.000,0.000,0.000|FS:0,0>",
        "<Sleep|MPos:0.000,0.000,0.000|FS:0,0>",
    ],
)
def test_a_board_that_reads_its_lines_at_connect_is_not_called_busy(report: str) -> None:
    """Alarm, Check and Sleep parse lines like Idle (`$I` is answered): nothing to wait
    for, and no operator told of moves of before that are not there."""
    grbl = Grbl()
    grbl.session.open()
    grbl.feed(BANNER)
    grbl.feed(report)
    assert occupied(grbl) == [] and told(grbl) == []
    assert grbl.session.occupied() is None
    grbl.feed(*VER)
    assert grbl.lines()[-1] == b"$$\n"


def test_a_board_behind_its_safety_door_is_told_so_not_to_be_reset() -> None:
    grbl = Grbl()
    grbl.session.open()
    grbl.feed(BANNER)
    grbl.feed("<Door:1|MPos:0.000,0.000,0.000|FS:0,0>")
    assert [e.board_state for e in occupied(grbl)] == ["Door"]
    message = told(grbl)[-1]
    assert "safety door" in message and "machine.cycle_start resumes it" in message
    assert "machine.reset empties it" not in message
    assert grbl.lines() == [b"$I\n"]  # `$I` waits behind the door


def test_a_board_through_its_moves_is_no_longer_shown_busy_and_is_told_again_later() -> None:
    grbl = Grbl()
    grbl.session.open()
    grbl.feed(BANNER)
    grbl.feed(HOLD)
    assert grbl.session.occupied() is not None
    grbl.feed(IDLE)  # through: the dashboard stops showing "connecting: Hold"
    assert grbl.session.occupied() is None
    grbl.feed(HOLD)  # held again (a button) before `$I` was read: told again
    assert [e.board_state for e in occupied(grbl)] == ["Hold", "Hold"]


def test_once_through_its_moves_the_build_gets_a_whole_handshake_timeout() -> None:
    """The handshake waited on the moves; the `$I` behind them is read only now, and may
    be answered up to a handshake timeout later, not one counted from the last busy
    report."""
    grbl = Grbl(handshake_timeout=2.0)
    grbl.session.open()
    grbl.feed(BANNER)
    grbl.at(1.0)
    grbl.feed(HOLD)  # busy: the handshake waits until 3.0 at least
    grbl.at(2.9)
    grbl.feed(IDLE)  # through at last (its polls went unanswered meanwhile)
    grbl.at(3.5)
    assert closed(grbl) == []
    grbl.feed(*VER)
    grbl.feed("$32=0", "ok")
    grbl.feed("$N0=", "$N1=", "ok")
    grbl.feed(*MODES)
    grbl.feed(IDLE)
    assert grbl.events[-1] == Ready() and closed(grbl) == []


def test_settings_refused_by_a_board_gone_busy_ask_after_it_and_wait() -> None:
    """A board idle at `$I` that starts a cycle before `$$` (a button, an SD card): no
    report is due, yet it is asked for one, and polled while it runs, for longer than
    the handshake timeout, then the handshake starts again from `$I`."""
    grbl = Grbl(handshake_timeout=2.0, status_interval=0.25)
    grbl.session.open()
    grbl.feed(BANNER)
    grbl.feed(IDLE, *VER)
    asked = len(grbl.realtime())
    grbl.feed("error:8")
    assert len(grbl.realtime()) == asked + 1  # a `?`, at once
    for step in range(1, 17):  # 4 s of a running board, answering each poll
        grbl.feed(RUN)
        grbl.at(step * 0.25)
    assert closed(grbl) == [] and Ready() not in grbl.events
    grbl.feed(IDLE)
    assert grbl.lines()[-1] == b"$I\n"
    finish_handshake(grbl)
    assert grbl.events[-1] == Ready()


def test_startup_blocks_refused_by_a_board_gone_busy_are_read_before_it_is_ready() -> None:
    """`$N` refused with error:8: the startup blocks a stop's reset would run are not
    known, so the handshake does not go on to `$G` and Ready without them."""
    grbl = Grbl()
    grbl.session.open()
    grbl.feed(BANNER)
    grbl.feed(IDLE, *VER)
    grbl.feed("$32=0", "ok")
    assert grbl.lines()[-1] == b"$N\n"
    grbl.feed("error:8")
    grbl.feed(RUN)
    assert grbl.lines()[-1] == b"$N\n"  # not `$G`
    assert Ready() not in grbl.events
    grbl.feed(IDLE)
    assert grbl.lines()[-1] == b"$I\n"
    finish_handshake(grbl)
    assert grbl.events[-1] == Ready()
    assert grbl.session.model.startup_blocks == []


def test_a_late_banner_after_the_build_was_asked_asks_it_no_second_time() -> None:
    """`$I` once: a banner read after `$I` went without one (BANNER_WAIT) asks nothing
    more, else each of the handshake's lines goes twice."""
    grbl = Grbl()
    grbl.session.open()
    grbl.at(BANNER_WAIT)
    assert grbl.lines() == [b"$I\n"]
    grbl.feed(BANNER)
    assert grbl.lines() == [b"$I\n"]
    grbl.feed(IDLE)
    finish_handshake(grbl)
    assert grbl.events[-1] == Ready()
    assert grbl.lines() == [b"$I\n", b"$$\n", b"$N\n", b"$G\n"]


def busy_and_reset(grbl: Grbl) -> None:
    """A board found running refuses `$I`; the operator's machine.reset empties it."""
    grbl.session.open()
    grbl.feed(BANNER)
    grbl.feed(RUN, "error:8")
    grbl.session.reset()
    grbl.pump()
    assert grbl.realtime()[-1] == b"\x18"


def test_a_reset_while_connecting_asks_the_build_once_more_only() -> None:
    grbl = Grbl()
    busy_and_reset(grbl)
    grbl.feed(BANNER)
    assert grbl.lines() == [b"$I\n", b"$I\n"]
    grbl.feed(IDLE)  # the refusal before the reset is not asked after again
    assert grbl.lines() == [b"$I\n", b"$I\n"]
    finish_handshake(grbl)
    assert grbl.events[-1] == Ready()
    assert grbl.lines()[2:] == [b"$$\n", b"$N\n", b"$G\n"]


def test_a_reset_while_connecting_shows_the_board_busy_no_more() -> None:
    grbl = Grbl()
    busy_and_reset(grbl)
    assert grbl.session.occupied() is not None
    grbl.feed(BANNER)  # it emptied itself: nothing of before runs
    assert grbl.session.occupied() is None


def test_a_reset_while_connecting_gives_the_handshake_its_whole_time_again() -> None:
    grbl = Grbl(handshake_timeout=2.0)
    grbl.session.open()
    grbl.feed(BANNER)
    grbl.at(1.5)
    grbl.feed(RUN, "error:8")  # busy: the handshake waits until 3.5 at least
    grbl.at(3.0)
    grbl.session.reset()
    grbl.pump()
    grbl.feed(BANNER)
    grbl.feed(IDLE)
    grbl.at(4.0)
    assert closed(grbl) == []
    finish_handshake(grbl)
    assert grbl.events[-1] == Ready()


def test_a_reset_just_before_the_first_report_does_not_skip_the_handshake() -> None:
    """Reset with `$G` answered and its report awaited: the board forgot every line, and
    the report after the new banner is not the handshake's end."""
    grbl = Grbl()
    grbl.session.open()
    grbl.feed(BANNER)
    grbl.feed(IDLE, *VER)
    grbl.feed("$32=0", "ok")
    grbl.feed("$N0=", "$N1=", "ok")
    grbl.feed(*MODES)  # a first report is asked now
    grbl.session.reset()
    grbl.pump()
    grbl.feed(BANNER)
    grbl.feed(IDLE)
    assert Ready() not in grbl.events
    assert grbl.lines()[-1] == b"$I\n"
    finish_handshake(grbl)
    assert grbl.events[-1] == Ready()


def test_answers_of_before_the_build_is_asked_are_dropped_not_a_fault() -> None:
    """grblHAL on native USB prints no banner: a job's `ok`s of before this link, read in
    the BANNER_WAIT before `$I` goes, are no fault of the link."""
    grbl = Grbl()
    grbl.session.open()
    grbl.feed("ok", "ok", "error:20")
    assert not [e for e in grbl.events if isinstance(e, Detected)]
    grbl.at(BANNER_WAIT)
    assert grbl.lines() == [b"$I\n"]
    grbl.feed(IDLE)
    grbl.feed("[VER:1.1f.20240101:]", "[OPT:VNMZL,100,1024]", "[FIRMWARE:grblHAL]", "ok")
    grbl.feed("$32=0", "ok")
    grbl.feed("$N0=", "$N1=", "ok")
    grbl.feed(*MODES)
    grbl.feed(IDLE)
    assert grbl.events[-1] == Ready()
    assert not [e for e in grbl.events if isinstance(e, Detected)]


def test_an_answer_of_before_with_a_message_is_not_taken_for_the_builds() -> None:
    """A job's `M2` prints `[MSG:Pgm End]` before its `ok`: that is not `$I`'s printout,
    and taken for it the board's build and receive buffer would be unknown."""
    grbl = Grbl()
    grbl.session.open()
    grbl.at(BANNER_WAIT)
    grbl.feed("[MSG:Pgm End]", "ok")
    assert grbl.lines() == [b"$I\n"]  # still `$I`'s answer awaited
    grbl.feed(IDLE)
    grbl.feed("[VER:1.1f.20240101:]", "[OPT:VNMZL,100,1024]", "[FIRMWARE:grblHAL]", "ok")
    assert grbl.lines()[-1] == b"$$\n"
    assert grbl.session.rx_size == 1024


def test_an_answer_with_no_line_waiting_once_ready_is_still_a_fault() -> None:
    """Only the handshake drops answers of before this link: once ready, an `ok` with no
    line waiting means the books and the board disagree."""
    grbl = Grbl()
    grbl.connect()
    grbl.feed("ok")
    faults = [e for e in grbl.events if isinstance(e, Detected)]
    assert [f.fault for f in faults] == ["lexical"]


def test_a_board_found_busy_is_polled_on_the_deadlines_the_session_names() -> None:
    """The engine sleeps until `next_deadline` and ticks then: while the handshake waits
    on a busy board, that is its next poll, not the handshake's timeout, or the board
    goes unpolled and the link is given up as silent."""
    grbl = Grbl(handshake_timeout=2.0, status_interval=0.25)
    grbl.session.open()
    grbl.feed(BANNER)
    grbl.feed(HOLD)
    polls = len(grbl.realtime())
    for _ in range(40):  # as the engine's timer does
        deadline = grbl.session.next_deadline()
        assert deadline is not None and deadline <= grbl.now + 0.25
        sent = grbl.at(deadline)
        if sent:
            grbl.feed(HOLD)  # each `?` answered: it holds on
    assert grbl.now >= 5.0 and closed(grbl) == []
    assert len(grbl.realtime()) >= polls + 20


def test_an_early_tick_does_not_poll_a_busy_board_before_its_time() -> None:
    """The engine may wake early (another deadline, a timer armed sooner): a board found
    busy is polled every `status_interval`, not at every wake-up."""
    grbl = Grbl(handshake_timeout=2.0, status_interval=0.25)
    grbl.session.open()
    grbl.feed(BANNER)
    grbl.feed(HOLD)
    polls = len(grbl.realtime())
    grbl.at(0.1)
    grbl.at(0.2)
    assert len(grbl.realtime()) == polls
    grbl.at(0.25)
    assert len(grbl.realtime()) == polls + 1


def test_nothing_is_written_to_a_board_before_its_banner_but_at_the_banner_wait() -> None:
    """An Arduino's bootloader runs for the first 1.5 s: no `?` is polled into it."""
    grbl = Grbl(status_interval=0.25)
    grbl.session.open()
    for step in range(1, 8):
        grbl.at(step * 0.25)
    assert grbl.now < BANNER_WAIT and grbl.written == []
    grbl.feed(BANNER)
    assert grbl.lines() == [b"$I\n"] and grbl.realtime() == [b"?"]
    grbl.feed(IDLE, *VER)
    grbl.at(grbl.now + 1.0)  # a board at rest, answering: no polls in the handshake
    assert grbl.realtime() == [b"?"]


def test_startup_blocks_refused_after_a_reset_go_on_to_the_modes() -> None:
    """After our reset a startup block may run at once (startup_motion): `$N` is refused
    while it moves. That is no board busy with moves of before: the blocks were read
    at connect, and the handshake goes on to `$G` and its report."""
    grbl = Grbl(startup_motion=True)
    grbl.connect(startup=("G0 X10", ""))
    grbl.session.reset()
    grbl.pump()
    grbl.feed(BANNER)
    assert grbl.lines()[-1] == b"$N\n"
    polls = len(grbl.realtime())
    grbl.feed("error:8")
    assert grbl.lines()[-1] == b"$G\n"  # not the whole handshake again from `$I`
    assert len(grbl.realtime()) == polls  # nor a wait on a board that is no one's to wait on
    grbl.feed(*MODES)
    grbl.feed(RUN)  # the first report: the block's move
    assert grbl.events[-1] == Ready()
    assert occupied(grbl) == []


def test_a_startup_block_moving_after_our_reset_is_not_told_as_moves_of_before() -> None:
    """A report of the block's move read while the re-sync's `$N` or `$G` is out: the
    board was just emptied by the reset, so nothing is "busy with moves it was given
    before", no exception says so, and a Machine told of an unwatched run must not stop
    the block (no `Occupied`)."""
    grbl = Grbl(startup_motion=True)
    grbl.connect(startup=("G0 X10", ""))
    grbl.session.reset()
    grbl.pump()
    grbl.feed(BANNER)
    grbl.feed("error:8")  # `$N`, refused while the block moves
    grbl.feed(RUN)  # read before `$G` is answered
    assert occupied(grbl) == []
    assert grbl.session.occupied() is None
    assert not any(
        isinstance(e, Excepted) and "moves it was given before" in str(e.fields)
        for e in grbl.events
    )
    grbl.feed(*MODES)
    grbl.feed(RUN)
    assert grbl.events[-1] == Ready()


def test_the_modes_are_pending_while_any_poll_of_them_is_out() -> None:
    """A jog or an operation waits for the `$G` after a client's `G20` (`modes_known`),
    wherever it is among the lines in flight."""
    grbl = Grbl()
    grbl.connect()
    grbl.session.send("G20", object())
    grbl.session.send("G0 X1", object())
    grbl.pump()
    grbl.feed("ok")  # `G20`: its `$G` goes behind `G0 X1`
    assert grbl.lines()[-1] == b"$G\n"
    assert grbl.session.modes_pending()
    grbl.session.send("G0 X2", object())
    grbl.pump()
    assert grbl.session.modes_pending()  # a line behind it changes nothing
    grbl.feed("ok")  # `G0 X1`: a `$G` of its own
    grbl.feed(*MODES)  # the first `$G`: the second is still out
    assert grbl.session.modes_pending()
    grbl.feed("ok")  # `G0 X2`
    grbl.feed(*MODES)
    grbl.feed(*MODES)
    assert not grbl.session.modes_pending()
