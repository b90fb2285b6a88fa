"""grbl's session: which lines leave a lockout, and when there is nothing to leave.

`$X` and `$H` leave an ALARM; an e-stop, a failed self test and Sleep (the
common SHUTDOWN) are left only by a reset (docs/dialects.md, grbl's Lockouts
row): a line sent to leave them another way is refused on the host, never
written. Out of a lockout machine.clear has nothing to clear and writes nothing.
"""

from __future__ import annotations

import pytest

from hostd.protocol.errors import Rejected
from hostd.protocol.states import MachineState as S
from tests.protocol.test_grbl_session import Grbl


@pytest.mark.parametrize("line", ["$X", "$H"])
@pytest.mark.parametrize(
    "how",
    ["ALARM:16", "<Sleep|MPos:0.000,0.000,0.000|FS:0,0>"],
    ids=["selftest-failed", "sleep"],
)
def test_a_shutdown_is_not_left_by_an_unlock_sent_as_a_line(how: str, line: str) -> None:
    grbl = Grbl()
    grbl.connect()
    grbl.feed(how)
    assert grbl.session.model.state is S.SHUTDOWN
    with pytest.raises(Rejected) as refused:
        grbl.session.send(line, object())
    assert refused.value.code == 205
    grbl.pump()
    assert grbl.lines() == []


@pytest.mark.parametrize(
    "report",
    [
        "<Idle|MPos:0.000,0.000,0.000|FS:0,0>",
        "<Hold:0|MPos:0.000,0.000,0.000|FS:0,0>",
        "<Door:0|MPos:0.000,0.000,0.000|FS:0,0>",
    ],
)
def test_clear_outside_an_alarm_has_nothing_to_clear_and_writes_nothing(report: str) -> None:
    grbl = Grbl()
    grbl.connect()
    grbl.feed(report)
    assert grbl.session.clear(object()) is False
    grbl.pump()
    assert grbl.lines() == []
