"""What a subscriber hears comes in causal order: the status report before what it caused.

A status report can move the supervisor (idle to busy) and raise a fault
(the board's e-stop). A client that reads `supervisor: busy` or `fault:
estop` must already have read the report that says why, so that what it
shows never runs ahead of what the board said.
"""

from __future__ import annotations

from typing import Any

import pytest

from hostd.protocol.states import MachineState
from tests.daemon.conftest import Rpc, Running

pytestmark = pytest.mark.asyncio

TOPICS = ["status", "supervisor", "fault"]


async def heard_until(rpc: Rpc, last: Any) -> list[dict[str, Any]]:
    """Every notification up to and including the first that `last` accepts."""
    heard: list[dict[str, Any]] = []
    await rpc.notification(lambda n: heard.append(n) is None and last(n))
    return heard


def state(note: dict[str, Any]) -> object:
    """The state a status notification left the machine in (the board's report of it, or
    the lockout it announced before its reports caught up: g2core.md)."""
    return note["params"]["snapshot"]["state"]["name"] if note["method"] == "status" else None


async def test_the_report_that_makes_the_machine_busy_comes_before_the_supervisor_change(
    hostd: Running, rpc: Rpc
) -> None:
    await rpc.call("subscribe", topics=TOPICS, machine="sim1")
    await rpc.call("machine.send", machine="sim1", line="G0 X20")
    heard = await heard_until(
        rpc, lambda n: n["method"] == "supervisor" and n["params"]["to"] == "busy"
    )
    assert heard[-1]["params"]["from"] == "idle"
    # The change is told right after the report it was decided on; that report is the first
    # to show the move (or, read before the board started it, the first after the line went).
    assert len(heard) >= 2 and heard[-2]["method"] == "status"
    assert heard[-2]["params"]["snapshot"]["supervisor"] == "idle"  # as it was when reported
    await hostd.idle(rpc)


async def test_the_report_of_an_e_stop_comes_before_the_fault_it_raises(
    hostd: Running, rpc: Rpc
) -> None:
    await rpc.call("subscribe", topics=TOPICS, machine="sim1")
    hostd.daemon.sims["sim1"].estop(True)  # type: ignore[union-attr]
    heard = await heard_until(
        rpc,
        lambda n: (
            n["method"] == "fault"
            and n["params"]["fault"]["id"] == "estop"
            and n["params"]["fault"]["active"]
        ),
    )
    shutdown = [i for i, n in enumerate(heard) if state(n) == MachineState.SHUTDOWN.name]
    assert shutdown, "the fault was heard before any report of the SHUTDOWN that raised it"
    # Nothing but that report's own consequences between it and the fault.
    assert all(n["method"] != "status" for n in heard[shutdown[0] + 1 : -1])
