"""The API's jog and send wait for grbl's modes after a client's `G20`.

grbl reports its units only in `$G`'s answer, which the session asks after each
client's line (tests/machine/test_grbl_modes_race.py). What judges distances
waits for that answer first (`operations.modes_known`): the API's machine.jog
and machine.send, and every operation, which is admitted (and keeps others out)
before it waits. A `$G` never answered refuses rather than guesses. Over a real
pty against hostd's simulated grbl, with the `$G` held in the board's input.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest

from hostd.api.methods.machine import JogParams, MachineMethods, SendParams
from hostd.api.rpc import RpcError
from hostd.machine import operations
from hostd.machine.machine import Machine
from hostd.protocol.errors import Busy, ControllerTimeout
from tests.machine.test_grbl import GRBL, grbl_bench
from tests.machine.test_grbl_modes_race import g20_with_its_modes_poll_held

pytestmark = pytest.mark.asyncio


class _Api:
    """What MachineMethods asks of the API: its one machine."""

    def __init__(self, machine: Machine) -> None:
        self._machine = machine

    def machine(self, _id: str) -> Machine:
        return self._machine


def methods(machine: Machine) -> MachineMethods:
    return MachineMethods(_Api(machine))  # type: ignore[arg-type]


async def still_waiting(task: asyncio.Future[Any]) -> None:
    """The task has not finished a while after it began: the held `$G` keeps it."""
    await asyncio.sleep(0.1)
    assert not task.done()


async def test_the_api_jog_right_after_g20_is_bounded_in_inches(tmp_path: Path) -> None:
    async with grbl_bench(tmp_path, GRBL) as bench:
        machine = bench.machine
        await g20_with_its_modes_poll_held(bench)
        params = JogParams(machine=machine.id, axes={"x": 20.0}, feed=100.0)
        jog = asyncio.ensure_future(methods(machine).machine_jog(params))
        await still_waiting(jog)
        bench.board.queue_input(False)
        with pytest.raises(RpcError, match="more than the axis travels"):
            await jog  # 20 in is 508 mm: past the 200 mm travel
        assert not [t for t in bench.recorder.tx() if t.startswith("$J=")]


async def test_an_api_send_of_a_jog_right_after_g20_is_judged_in_inches(tmp_path: Path) -> None:
    async with grbl_bench(tmp_path, GRBL) as bench:
        machine = bench.machine
        await g20_with_its_modes_poll_held(bench)
        params = SendParams(machine=machine.id, line="$J=G91 X20 F100")
        send = asyncio.ensure_future(methods(machine).machine_send(params))
        await still_waiting(send)
        bench.board.queue_input(False)
        with pytest.raises(RpcError, match="more than the axis travels"):
            await send
        assert not [t for t in bench.recorder.tx() if t.startswith("$J=")]


async def test_modes_never_answered_refuse_the_jog_rather_than_guess(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(operations, "ANSWER_WAIT", 0.3)
    async with grbl_bench(tmp_path, GRBL) as bench:
        await g20_with_its_modes_poll_held(bench)  # and held on
        with pytest.raises(ControllerTimeout, match="its modes were not answered"):
            await operations.modes_known(bench.machine)
        bench.board.queue_input(False)


async def test_an_operation_waiting_for_the_modes_keeps_others_out(tmp_path: Path) -> None:
    """One operation at a time, counted from its admission: a second one asked while the
    first waits for the modes is refused, not run alongside it once they come."""
    async with grbl_bench(tmp_path, GRBL) as bench:
        machine = bench.machine
        await g20_with_its_modes_poll_held(bench)
        first = asyncio.ensure_future(operations.spindle(machine, "off", None))
        await still_waiting(first)
        with pytest.raises(Busy, match="already running an operation"):
            await asyncio.wait_for(operations.spindle(machine, "off", None), 2.0)
        bench.board.queue_input(False)
        await first
