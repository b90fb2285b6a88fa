"""Each machine answers in its dialect's words, through the real socket (issue 28).

A g2core board and a grbl board side by side on real ptys, reached through
the real Unix socket: a refused line is error 1005 with the firmware's own
text for its own number, for every number its registry entry lists (each
simulator answers the next line with the code a test names: `refuse_next`),
`machine.alarm` and `machine.shutdown` are what the dialect has (g2core's
JSON, or a clear refusal on grbl), and a `?` on grbl answers in grbl's names.
The same codes by plain calls on each session are in
tests/protocol/test_dialect_words.py.
"""

from __future__ import annotations

import pytest

from hostd.protocol import dialects
from hostd.protocol.grbl.codes import ERRORS
from hostd.protocol.status import MESSAGES
from tests.daemon.conftest import G2, GRBL, Rpc, Running
from tests.daemon.test_api import fails

pytestmark = pytest.mark.asyncio


@pytest.mark.parametrize(
    ("line", "code"),
    [
        ("G1 X1 Q5", 20),  # an unsupported word: "Internal error" in g2core's table
        ("G0 G1 X1", 21),  # two motions from one modal group
        ("G4", 28),  # a dwell with no P
    ],
)
async def test_a_grbl_refusal_is_in_grbls_words(
    both: tuple[Running, Rpc], line: str, code: int
) -> None:
    _, rpc = both
    err = await fails(1005, rpc.call("machine.send", machine=GRBL, line=line))
    assert err.data == {"status": code, "msg": ERRORS[code]}
    assert ERRORS[code] in err.message and MESSAGES.get(code, "?") not in err.message


@pytest.mark.parametrize(("machine", "dialect"), [(G2, "g2core"), (GRBL, "grbl")])
async def test_every_status_a_dialect_answers_comes_back_in_its_own_words(
    both: tuple[Running, Rpc], machine: str, dialect: str
) -> None:
    hostd, rpc = both
    sim = hostd.daemon.sims[machine]
    statuses = dialects.lookup(dialect).words.statuses
    other = dialects.lookup("grbl" if dialect == "g2core" else "g2core").words.statuses
    assert len(statuses) > 50  # the whole table, not a sample
    for code, text in statuses.items():
        sim.refuse_next(code)
        err = await fails(1005, rpc.call("machine.send", machine=machine, line="G0 X1"))
        assert err.data == {"status": code, "msg": text}, code
        assert err.message.endswith(f"controller answered {code}: {text}"), code
        assert other.get(code) in (None, text) or err.data["msg"] != other[code], code
        if (await rpc.call("machine.status", machine=machine))["lockout"] is not None:
            # A lockout's own refusal (g2core's 204-206): the host takes the board to be
            # in that lockout, as it should, until a reset says otherwise.
            await rpc.call("machine.reset", machine=machine)
            await hostd.idle(rpc, machine)
    # The board is none the worse: the next line runs.
    assert (await rpc.call("machine.send", machine=machine, line="G0 X2"))["status"] == 0
    await hostd.idle(rpc, machine)
    assert (await rpc.call("machine.status", machine=machine))["lockout"] is None


async def test_a_g2core_refusal_is_in_g2cores_words(both: tuple[Running, Rpc]) -> None:
    _, rpc = both
    err = await fails(1005, rpc.call("machine.send", machine=G2, line="G5 X1"))
    status = err.data["status"]
    assert err.data == {"status": status, "msg": MESSAGES[status]}


async def test_grbl_refuses_a_host_raised_alarm_or_shutdown(both: tuple[Running, Rpc]) -> None:
    hostd, rpc = both
    sim = hostd.daemon.sims[GRBL]
    before = len(sim.received)
    for method, word in (("machine.alarm", "alarm"), ("machine.shutdown", "shutdown")):
        err = await fails(-32602, rpc.call(method, machine=GRBL))
        assert f"no host-raised {word}" in err.message and err.data == {"refusal": "unreadable"}
    assert not any(b"{" in r.data for r in list(sim.received)[before:])  # no g2core JSON went
    snap = await rpc.call("machine.status", machine=GRBL)
    assert snap["state"]["name"] == "READY" and snap["supervisor"] == "idle"
    # g2core still raises both with its own JSON.
    await rpc.call("subscribe", topics=["status"], machine=G2)
    assert await rpc.call("machine.alarm", machine=G2) == {}
    await rpc.notification(
        lambda n: n["method"] == "status" and n["params"]["snapshot"]["state"]["name"] == "ALARM"
    )


async def test_a_query_on_grbl_answers_in_grbls_names(both: tuple[Running, Rpc]) -> None:
    _, rpc = both
    await rpc.call("machine.send", machine=GRBL, line="G0 X2 Y3")
    answer = await rpc.call("machine.send", machine=GRBL, line="?")
    report = answer["r"]["report"]
    assert answer["status"] == 0 and set(answer["r"]) == {"report"}
    assert report["state"] in ("Idle", "Run")
    assert {"MPos", "FS"} <= set(report) or {"WPos", "FS"} <= set(report)
    position = report.get("MPos") or report["WPos"]
    assert len(position) >= 3 and all(isinstance(v, float) for v in position)
    assert "stat" not in report and "posx" not in report  # g2core's names
