"""g2core's spindle in the snapshot: the keys the board has, asked at the handshake.

Master's 100.26 reports `spe`/`spd`/`sps`, edge from 101.03 `spc`/`sps`, and
an edge 100.x had `spc` too, so the build number cannot say which
(hostd/protocol/g2handshake.py SPINDLE_KEYS). A key a board lacks would
have it refuse the whole report list, and the handshake would fail.
"""

from __future__ import annotations

import json
from typing import Any

from hostd.protocol.vocabulary import Closing
from tests.protocol.g2wire import BANNER, Wire

UNRECOGNIZED_NAME = 100  # json_parser.cpp:169


def handshake(wire: Wire, spindle: dict[bytes, dict[str, Any] | None]) -> list[dict[str, Any]]:
    """The whole handshake; `spindle` answers the spindle GETs (None: refused, 100)."""
    wire.session.open()
    wire.feed(BANNER)
    while not wire.session.ready:
        line = wire.unanswered[0]
        if line.rstrip() in spindle:
            body = spindle[line.rstrip()]
            wire.answer(line, body or {}, status=0 if body is not None else UNRECOGNIZED_NAME)
        else:
            wire.answer(line)
    assert not wire.of(Closing)
    return [json.loads(x) for x in wire.lines()]


def report_list(sent: list[dict[str, Any]]) -> set[str]:
    (listed,) = [x["sr"] for x in sent if isinstance(x.get("sr"), dict)]
    return set(listed)


def test_an_edge_board_lists_spc_and_sps_and_is_read_at_once() -> None:
    wire = Wire()
    sent = handshake(wire, {b'{"spc":null}': {"spc": 1}})
    assert next(iter(sent[0])) == "spc"  # asked before anything is set
    listed = report_list(sent)
    assert {"spc", "sps"} <= listed and not {"spe", "spd"} & listed
    assert not any("spe" in x for x in sent)  # one answer was enough
    assert wire.session.model.snapshot()["spindle"] == {"state": "cw", "speed": None}
    wire.report(spc=2, sps=12000)
    assert wire.session.model.snapshot()["spindle"] == {"state": "ccw", "speed": 12000.0}
    wire.report(spc=3)  # paused in a hold: it stands still
    assert wire.session.model.snapshot()["spindle"]["state"] == "off"


def test_a_master_board_refuses_spc_and_lists_spe_spd_sps() -> None:
    wire = Wire(100.26)
    sent = handshake(wire, {b'{"spc":null}': None, b'{"spe":null}': {"spe": 0}})
    assert [next(iter(x)) for x in sent[:3]] == ["spc", "spe", "ej"]
    listed = report_list(sent)
    assert {"spe", "spd", "sps"} <= listed and "spc" not in listed
    model = wire.session.model
    assert model.snapshot()["spindle"]["state"] == "off"
    wire.report(spe=1, spd=1, sps=9000)
    assert model.snapshot()["spindle"] == {"state": "ccw", "speed": 9000.0}
    wire.report(spd=0)  # a filtered report: only what changed
    assert model.snapshot()["spindle"]["state"] == "cw"
    wire.report(spe=2)  # SPINDLE_PAUSE: it was on and is stopped now
    assert model.snapshot()["spindle"]["state"] == "off"
    wire.report(spe=1)
    assert model.snapshot()["spindle"]["state"] == "cw"
    wire.report(spe=0)
    assert model.snapshot()["spindle"] == {"state": "off", "speed": 9000.0}


def test_a_board_with_neither_lists_no_spindle_and_still_connects() -> None:
    wire = Wire()
    sent = handshake(wire, {b'{"spc":null}': None, b'{"spe":null}': None})
    assert not {"spc", "sps", "spe", "spd"} & report_list(sent)
    assert wire.session.ready
    assert wire.session.model.snapshot()["spindle"] is None


def test_the_board_is_asked_again_on_every_connection() -> None:
    """A board reflashed between two connections may have the other keys."""
    wire = Wire()
    handshake(wire, {b'{"spc":null}': {"spc": 0}})
    wire.session.close("unplugged")
    wire.clear()
    sent = handshake(wire, {b'{"spc":null}': None, b'{"spe":null}': {"spe": 0}})
    assert {"spe", "spd", "sps"} <= report_list(sent)
    assert "spc" not in report_list(sent)
