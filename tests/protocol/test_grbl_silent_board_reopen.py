"""grbl's session: a silent board that may be moving is given up, not reopened.

Reopening an Arduino's port resets it, which stops a move dead and loses the
position (docs/dialects.md, grbl's Liveness row). A board whose last report
said Idle may still have started a line written since: with a line of the
host's unanswered it may be moving, and its port is not reopened on its own.
"""

from __future__ import annotations

from hostd.protocol.vocabulary import Closing
from tests.protocol.test_grbl_session import Grbl


def test_a_board_silent_with_a_line_unanswered_is_not_reopened() -> None:
    grbl = Grbl(heartbeat=2.0, status_interval=0.25, link_silence=10.0)
    grbl.connect()  # its last report: Idle, the planner empty
    grbl.session.send("G0 X100", object())
    grbl.pump()
    for t in range(1, 13):
        grbl.at(float(t))
    (closing,) = [e for e in grbl.events if isinstance(e, Closing)]
    assert not closing.reopen and "may be moving" in closing.reason
