"""A grbl board found busy when its port opens: moves it was given before this link.

A daemon that died mid-job (or a job from grblHAL's SD card) leaves a board
running or holding moves. It answers `?` at once, but parses no line while
it holds moves, and refuses `$I`, `$$` and `$N` with error:8 outside Idle
and Alarm (gnea/grbl system.c:172-175; grblHAL core system.c:309, :635,
:726). The handshake waits for it, polling, instead of timing out and
reopening the port, and a stop asked meanwhile holds it, since its startup
blocks cannot be read (docs/dialects.md, "A board busy at connect").
"""

from __future__ import annotations

import pytest

from hostd.protocol.commands import Realtime
from hostd.protocol.errors import Busy
from hostd.protocol.grbl.connection import BANNER_WAIT
from hostd.protocol.vocabulary import Closing, Detected, Excepted, Occupied, Ready
from tests.protocol.test_grbl_session import IDLE, Grbl

HOLD = "<Hold:0|MPos:10.000,0.000,0.000|Bf:0,0|FS:0,8000>"
RUN = "<Run|MPos:5.000,0.000,0.000|Bf:0,0|FS:1000,8000>"
BANNER = "Grbl 1.1h ['$' for help]"


def finish_handshake(grbl: Grbl) -> None:
    """The answers to `$I`, `$$`, `$N` and `$G`, then the first report."""
    grbl.feed("[VER:1.1h.20190830:]", "[OPT:V,15,128]", "ok")
    grbl.feed("$32=0", "ok")
    grbl.feed("$N0=", "$N1=", "ok")
    grbl.feed("[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]", "ok")
    grbl.feed(IDLE)


def occupied(grbl: Grbl) -> list[Occupied]:
    return [e for e in grbl.events if isinstance(e, Occupied)]


def test_a_board_holding_moves_keeps_the_handshake_waiting_and_polled_not_reopened() -> None:
    grbl = Grbl(handshake_timeout=2.0, status_interval=0.25)
    grbl.session.open()
    grbl.feed(BANNER)
    assert grbl.lines() == [b"$I\n"] and grbl.realtime() == [b"?"]
    grbl.feed(HOLD)  # `$I` waits behind the moves it holds
    assert [e.board_state for e in occupied(grbl)] == ["Hold"]
    told = [e for e in grbl.events if isinstance(e, Excepted)]
    assert "busy with moves it was given before" in told[-1].fields["msg"]
    assert "machine.reset empties it" in told[-1].fields["msg"]
    # Ten handshake timeouts long, answered each poll: no Closing, a `?` a poll.
    for step in range(1, 81):
        grbl.at(step * 0.25)
        grbl.feed(HOLD)
    assert not [e for e in grbl.events if isinstance(e, Closing)]
    assert len(grbl.realtime()) >= 80
    assert len(occupied(grbl)) == 1  # told once, not at every report
    assert grbl.lines() == [b"$I\n"]  # nothing piled behind the moves
    # The operator resumes them elsewhere; they end; `$I` is read at last.
    grbl.feed(IDLE)
    finish_handshake(grbl)
    assert grbl.events[-1] == Ready()
    assert grbl.session.model.last_exception is not None  # what was told stays readable


def test_a_busy_board_that_goes_silent_ends_the_handshake() -> None:
    grbl = Grbl(handshake_timeout=2.0, status_interval=0.25)
    grbl.session.open()
    grbl.feed(BANNER)
    grbl.feed(RUN)
    grbl.at(1.9)
    assert not [e for e in grbl.events if isinstance(e, Closing)]
    grbl.at(2.1)  # its `?`s unanswered for the handshake's time: gone
    assert [e for e in grbl.events if isinstance(e, Closing)]


def test_a_build_refused_with_error_8_is_asked_again_once_the_board_is_at_rest() -> None:
    """A board running with room in its planner reads `$I` and refuses it: the handshake
    must not go on to `$$`, `$N` and a first report with the build and the startup
    blocks unknown (character counting against a guessed buffer)."""
    grbl = Grbl()
    grbl.session.open()
    grbl.feed(BANNER)
    grbl.feed(RUN, "error:8")
    assert grbl.lines() == [b"$I\n"]  # not `$$`
    assert [e.board_state for e in occupied(grbl)] == ["Run"]
    grbl.feed(RUN)
    assert grbl.lines() == [b"$I\n"]
    grbl.feed(IDLE)
    assert grbl.lines() == [b"$I\n", b"$I\n"]  # asked again, at rest
    finish_handshake(grbl)
    assert grbl.events[-1] == Ready()
    assert grbl.session.blocks == 15 and grbl.session.model.startup_blocks == []


def test_settings_refused_mid_handshake_start_it_again_from_the_build() -> None:
    grbl = Grbl()
    grbl.session.open()
    grbl.feed(BANNER)
    grbl.feed(IDLE, "[VER:1.1h.20190830:]", "[OPT:V,15,128]", "ok")
    assert grbl.lines()[-1] == b"$$\n"
    grbl.feed("error:8")  # a cycle began meanwhile (a button, an SD card)
    grbl.feed(RUN)
    assert grbl.lines()[-1] == b"$$\n" and Ready() not in grbl.events
    grbl.feed(IDLE)
    assert grbl.lines()[-1] == b"$I\n"
    finish_handshake(grbl)
    assert grbl.events[-1] == Ready()


def test_a_kill_while_connecting_holds_the_board_since_its_startup_blocks_are_unread() -> None:
    grbl = Grbl(handshake_timeout=2.0)
    grbl.session.open()
    grbl.feed(BANNER)
    grbl.feed(RUN)
    grbl.session.realtime(Realtime.JOB_KILL)  # the machine's, after a crash
    grbl.pump()
    assert b"!" in grbl.realtime()
    grbl.feed(HOLD.replace("Hold:0", "Hold:1"), HOLD, HOLD, HOLD)
    assert b"\x18" not in grbl.realtime()  # a reset would run blocks nobody read
    held = [e for e in grbl.events if isinstance(e, Excepted)][-1].fields["msg"]
    assert "held instead of reset" in held and "not read yet" in held
    with pytest.raises(Busy):
        grbl.session.realtime(Realtime.CYCLE_START)  # `~` would run the moves it holds
    # The operator's machine.reset: the board empties itself, `$I` with it, and restarts.
    grbl.session.reset()
    grbl.pump()
    assert grbl.realtime()[-1] == b"\x18"
    grbl.feed(BANNER)
    assert grbl.lines() == [b"$I\n", b"$I\n"]
    grbl.feed(IDLE)
    finish_handshake(grbl)
    assert grbl.events[-1] == Ready()
    assert grbl.session.model.state is not None and grbl.session.model.state.is_resting


def test_a_kill_while_connecting_resets_at_rest_where_startup_motion_allows() -> None:
    grbl = Grbl(startup_motion=True)
    grbl.session.open()
    grbl.feed(BANNER)
    grbl.feed(RUN)
    grbl.session.realtime(Realtime.JOB_KILL)
    grbl.pump()
    grbl.feed(RUN, HOLD.replace("Hold:0", "Hold:1"), HOLD)
    realtime = grbl.realtime()
    assert realtime.index(b"!") < realtime.index(b"\x18")  # at rest: no position lost
    grbl.feed(BANNER)
    assert grbl.lines() == [b"$I\n", b"$I\n"]
    grbl.feed(IDLE)
    finish_handshake(grbl)
    assert grbl.events[-1] == Ready()


def test_answers_of_before_this_link_are_not_taken_for_the_handshakes() -> None:
    """The board went on answering a job's lines after the link went, and the port kept
    what it printed: those `ok`s, read first, must not pass for `$I`'s answer (its
    build unknown, a 1,024-byte buffer counted as 128) nor raise a lexical fault."""
    grbl = Grbl()
    grbl.session.open()
    grbl.at(BANNER_WAIT)  # grblHAL on native USB: no banner
    assert grbl.lines() == [b"$I\n"]
    grbl.feed("ok", "ok", "error:20", "ok")
    assert grbl.lines() == [b"$I\n"]  # still `$I`'s answer awaited
    grbl.feed("[VER:1.1f.20240101:]", "[OPT:VNMZL,100,1024]", "[FIRMWARE:grblHAL]", "ok")
    assert grbl.lines()[-1] == b"$$\n"
    assert grbl.session.rx_size == 1024 and grbl.session.flavour == "GrblHAL"
    grbl.feed("$32=0", "ok")
    grbl.feed("$N0=", "$N1=", "ok")
    grbl.feed("[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]", "ok")
    grbl.feed(IDLE)
    assert grbl.events[-1] == Ready()
    assert not [e for e in grbl.events if isinstance(e, Detected)]


def test_a_build_with_no_startup_lines_answers_n_with_a_bare_ok_and_connects() -> None:
    """Only `$I`'s answer must show its printout (`[VER:]`): every answer of before this
    link comes ahead of it, and the lines after it are answered in order. A build whose
    `$N` prints no line (no startup lines) still connects."""
    grbl = Grbl()
    grbl.session.open()
    grbl.feed(BANNER)
    grbl.feed("ok")  # of before: dropped
    grbl.feed("[VER:1.1h.20190830:]", "[OPT:V,15,128]", "ok")
    grbl.feed("$32=0", "ok")
    assert grbl.lines()[-1] == b"$N\n"
    grbl.feed("ok")  # no `$N0=` line
    assert grbl.lines()[-1] == b"$G\n"
    grbl.feed("[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]", "ok")
    grbl.feed(IDLE)
    assert grbl.events[-1] == Ready()
