"""g2core's session across a lost link: a new connection starts from what the board says.

Pins `close` (g2connection.py): it settles everything the connection carried,
a flush awaiting its proof too. The board that answers the next handshake has
nothing of the old connection's queue; a wait kept from before would hold back
every data line of the new connection, with no deadline left to end it. And
after a reset (0x18) the handshake waits for the banner the rebooting board
prints, and goes on from it.
"""

from __future__ import annotations

import pytest

from hostd.protocol.commands import Realtime
from tests.protocol.g2wire import BUILDS, Wire, banner


@pytest.mark.parametrize("kill", [Realtime.QUEUE_FLUSH, Realtime.JOB_KILL], ids=["flush", "kill"])
@pytest.mark.parametrize("fb", BUILDS)
def test_a_flush_unproven_when_the_link_drops_does_not_hold_back_the_next_connection(
    fb: float, kill: Realtime
) -> None:
    wire = Wire(fb)
    wire.connect()
    wire.session.realtime(kill)
    wire.pump()
    wire.session.close("link lost")
    wire.unanswered.clear()
    wire.connect()
    assert not wire.session.flushing()
    wire.session.send("G0 X1", object())
    wire.pump()
    assert wire.lines()[-1] == b"G0 X1\n"


@pytest.mark.parametrize("fb", BUILDS)
def test_after_a_reset_the_boards_banner_starts_the_handshake(fb: float) -> None:
    """After 0x18 only the banner will do (`open(rebooting=True)` asks no version): the
    board that reboots prints it, and the handshake must go on from it to ready."""
    wire = Wire(fb)
    wire.connect()
    wire.session.reset()
    wire.session.close("controller reset", restarted=True)
    wire.unanswered.clear()
    wire.session.open(rebooting=True)
    wire.pump()
    assert wire.unanswered == []  # nothing asked: the banner is awaited
    wire.feed(banner(fb))
    assert wire.unanswered  # the protocol settings, the first of the handshake's steps
    while not wire.session.ready:
        wire.answer(wire.unanswered[0])
    assert wire.session.ready
