"""Each dialect answers in its own words: status texts, host-raised lockouts, `?` (issue 28).

Plain calls on each session, for every code its firmware can answer: the
board answers a client's line with the code, and the text the API shows
(error 1005's `msg`, which the engine takes from `status_text`) is the
firmware's own. The same through the real socket is in
tests/daemon/test_dialect_words.py.
"""

from __future__ import annotations

import pytest

from hostd.protocol.commands import InvalidCommand
from hostd.protocol.errors import ControllerError
from hostd.protocol.grbl.codes import ERRORS
from hostd.protocol.messages import Response
from hostd.protocol.status import MESSAGES
from tests.protocol.g2wire import Wire
from tests.protocol.test_grbl_session import Grbl

# The bug this guards: g2core's words for grbl's numbers.
G2CORE_ON_GRBL = {20: "Internal error", 5: "System shutdown"}


def _grbl_answers(code: int) -> ControllerError:
    """A client's line on a grbl board answered `error:<code>`, as the API reports it."""
    grbl = Grbl()
    grbl.connect()
    token = object()
    grbl.session.send("G1 X1 Q5", token)
    grbl.pump()
    grbl.feed(f"error:{code}")
    settled = grbl.settled(token)
    assert settled is not None and isinstance(settled.outcome, Response)
    assert settled.outcome.status == code and not settled.outcome.ok
    return ControllerError(code, grbl.session.status_text(settled.outcome.status))


def test_every_grbl_error_comes_back_in_grbls_words() -> None:
    for code, text in ERRORS.items():
        answered = _grbl_answers(code)
        assert answered.data == {"status": code, "msg": text}
        assert f"controller answered {code}: {text}" == str(answered.args[0])
    # Two read against grblHAL errors.c, where g2core's table says something else.
    assert _grbl_answers(20).data["msg"] == "Unsupported or invalid g-code command found in block."
    assert _grbl_answers(5).data["msg"].startswith("Homing cycle failure.")
    for code, g2core_text in G2CORE_ON_GRBL.items():
        assert MESSAGES[code] == g2core_text  # what the bug said
        assert _grbl_answers(code).data["msg"] != g2core_text


def test_a_grbl_error_no_table_knows_still_shows_its_number() -> None:
    msg = _grbl_answers(201).data["msg"]
    assert msg == "error 201" and msg != MESSAGES[201]


def _g2core_answers(code: int) -> ControllerError:
    """A client's line on a g2core board answered with status `code` in its footer."""
    wire = Wire()
    wire.connect()
    token = object()
    wire.session.send("G1 X1", token)
    wire.pump()
    line = next(x for x in wire.unanswered if not x.startswith(b"{"))
    wire.answer(line, {}, status=code)
    settled = wire.settled(token)
    assert settled is not None and isinstance(settled.outcome, Response), (code, settled)
    assert settled.outcome.status == code and not settled.outcome.ok
    return ControllerError(code, wire.session.status_text(settled.outcome.status))


def test_every_g2core_status_comes_back_in_g2cores_words() -> None:
    for code, text in MESSAGES.items():
        if code == 0:
            continue  # OK is no error
        assert _g2core_answers(code).data == {"status": code, "msg": text}
    assert _g2core_answers(20).data["msg"] == "Internal error"


def test_grbl_has_no_host_raised_alarm_or_shutdown() -> None:
    grbl = Grbl()
    grbl.connect()
    for ask, word in ((grbl.session.alarm_line, "alarm"), (grbl.session.shutdown_line, "shutdown")):
        with pytest.raises(InvalidCommand) as refused:
            ask()
        assert refused.value.code == -32602
        assert f"no host-raised {word}" in refused.value.message
    assert grbl.pump() == []  # nothing went to the board


def test_g2core_raises_its_lockouts_with_its_own_json() -> None:
    wire = Wire()
    assert (wire.session.alarm_line(), wire.session.shutdown_line()) == ("{alarm:n}", "{shutd:n}")


def test_a_query_on_grbl_answers_in_grbls_names() -> None:
    grbl = Grbl()
    grbl.connect()
    token = object()
    grbl.session.send("?", token)
    grbl.pump()
    grbl.feed("<Hold:0|MPos:1.500,-2.000,0.000|Bf:15,128|FS:500,0|Ln:42|Pn:XP|Ov:100,100,100|A:SF>")
    settled = grbl.settled(token)
    assert settled is not None and isinstance(settled.outcome, Response)
    assert settled.outcome.body == {
        "report": {
            "state": "Hold:0",
            "MPos": [1.5, -2.0, 0.0],
            "Bf": [15, 128],
            "FS": [500, 0],
            "Ln": [42],
            "Pn": "XP",
            "Ov": [100, 100, 100],
            "A": "SF",
        }
    }
    assert "sr" not in settled.outcome.body  # g2core's name for a status report


def test_a_grbl_report_value_that_is_no_number_stays_text() -> None:
    grbl = Grbl()
    grbl.connect()
    token = object()
    grbl.session.send("?", token)
    grbl.pump()
    grbl.feed("<Idle|WPos:nan,1,2|WCO:1e999,0,0|H:1,7>")
    settled = grbl.settled(token)
    assert settled is not None and isinstance(settled.outcome, Response)
    report = settled.outcome.body["report"]
    assert report["WPos"] == "nan,1,2" and report["WCO"] == "1e999,0,0"
    assert report["H"] == [1, 7] and report["state"] == "Idle"
