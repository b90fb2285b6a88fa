"""Digital (`in1`..`in8`) and analogue (`ain1`..`ain4`) inputs as status report keys."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import serialx

from hostd.sim import SimConfig, SimController

from .conftest import Host, Message

pytestmark = pytest.mark.asyncio


LISTED = {"stat": 1, "in4": 0, "ain1": 0}


def reports(messages: list[Message]) -> list[dict[str, Any]]:
    """The automatic status reports among `messages`."""
    return [m["sr"] for m in messages if "sr" in m]


def reported(key: str, value: object) -> Callable[[Message], bool]:
    return lambda m: "sr" in m and m["sr"].get(key) == value


async def list_inputs(host: Host) -> list[Message]:
    """Put in4 and ain1 in the report list; a new list is reported whole once, after the answer."""
    host.send(b"{sr:{stat:t,in4:t,ain1:t}}\n")
    return await host.until(lambda m: m == {"sr": LISTED}, timeout=1)


async def test_inputs_can_be_put_in_the_status_report_list(host: Host) -> None:
    got = await list_inputs(host)
    assert got[0] == {"r": {"sr": LISTED}, "f": [1, 0, 28]}


async def test_a_digital_input_change_is_reported_at_once(host: Host, sim: SimController) -> None:
    await list_inputs(host)
    sim.set_input(4, 1)
    got = await host.until(reported("in4", 1), timeout=1)
    assert reports(got)[-1] == {"in4": 1}  # filtered: only what changed
    sim.set_input(4, False)
    got = await host.until(reported("in4", 0), timeout=1)
    assert reports(got)[-1] == {"in4": 0}


async def test_an_analogue_input_change_is_reported_at_once(host: Host, sim: SimController) -> None:
    await list_inputs(host)
    sim.set_analog(1, 2.75)
    got = await host.until(reported("ain1", 2.75), timeout=1)
    assert reports(got)[-1] == {"ain1": 2.75}
    sim.set_analog(1, 31.0)
    await host.until(reported("ain1", 31), timeout=1)  # printed without a fraction


async def test_an_unchanged_input_sends_no_report(host: Host, sim: SimController) -> None:
    # At program end every report carries `stat`, so a needless report would show.
    assert (await host.ask(b"M2\n"))["f"][1] == 0
    host.send(b"{sr:{stat:t,in4:t,ain1:t}}\n")
    await host.until(lambda m: m == {"sr": {"stat": 4, "in4": 0, "ain1": 0}}, timeout=1)
    sim.set_input(4, 0)  # already 0
    sim.set_analog(1, 0.0001)  # below the reported precision
    sim.set_input(4, 1)
    got = await host.until(lambda m: "sr" in m, timeout=1)
    assert reports(got) == [{"in4": 1, "stat": 4}]


async def test_an_input_outside_the_list_is_not_reported(host: Host, sim: SimController) -> None:
    await list_inputs(host)
    sim.set_input(5, 1)
    sim.set_input(4, 1)
    got = await host.until(lambda m: "sr" in m, timeout=1)
    assert reports(got) == [{"in4": 1}]


async def test_inputs_can_be_queried(host: Host, sim: SimController) -> None:
    sim.set_input(8, True)
    sim.set_analog(4, 12.5)
    assert (await host.ask(b"{in8:n}\n"))["r"] == {"in8": 1}
    assert (await host.ask(b"{ain4:n}\n"))["r"] == {"ain4": 12.5}
    assert (await host.ask(b"$in1\n"))["r"] == {"in1": 0}
    assert (await host.ask(b"{sr:n}\n"))["r"]["sr"].keys() >= {"stat", "posx"}


async def test_a_full_report_carries_the_listed_inputs(host: Host, sim: SimController) -> None:
    await list_inputs(host)
    sim.set_input(4, 1)
    sim.set_analog(1, 3.5)
    assert (await host.ask(b"{sr:n}\n"))["r"] == {"sr": {"stat": 1, "in4": 1, "ain1": 3.5}}


async def test_inputs_are_read_only(host: Host) -> None:
    assert (await host.ask(b"{in4:1}\n"))["f"][1] == 104


async def test_an_unknown_input_is_not_a_key(host: Host) -> None:
    assert (await host.ask(b"{in9:n}\n"))["f"][1] == 100
    assert (await host.ask(b"{sr:{stat:t,ain5:t}}\n"))["f"][1] == 100


async def test_inputs_survive_a_reset(sim: SimController) -> None:
    sim.set_input(2, 1)
    sim.set_analog(3, 1.25)
    assert sim.inputs == {f"in{n}": int(n == 2) for n in range(1, 9)} | {
        "ain1": 0,
        "ain2": 0,
        "ain3": 1.25,
        "ain4": 0,
    }
    await sim.reset()
    host = await Host.open(sim.data_path)
    try:
        assert (await host.ask(b"{in2:n}\n"))["r"] == {"in2": 1}
        assert (await host.ask(b"{ain3:n}\n"))["r"] == {"ain3": 1.25}
    finally:
        await host.close()


@pytest.mark.parametrize("n", [0, 9, -1, 4.0, True])
async def test_unknown_digital_inputs_are_refused(sim: SimController, n: Any) -> None:
    with pytest.raises(ValueError, match="no digital input"):
        sim.set_input(n, 1)


@pytest.mark.parametrize("n", [0, 5])
async def test_unknown_analogue_inputs_are_refused(sim: SimController, n: int) -> None:
    with pytest.raises(ValueError, match="no analogue input"):
        sim.set_analog(n, 1.0)


@pytest.mark.parametrize("value", [2, -1, 0.5])
async def test_a_digital_input_is_zero_or_one(sim: SimController, value: int) -> None:
    with pytest.raises(ValueError, match="0 or 1"):
        sim.set_input(1, value)


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
async def test_an_analogue_input_is_a_finite_number(sim: SimController, value: float) -> None:
    with pytest.raises(ValueError, match="finite"):
        sim.set_analog(1, value)


@pytest.mark.asyncio
async def test_history_keeps_only_the_most_recent_entries(tmp_path: Path) -> None:
    """A board inside the daemon runs for days: what it recorded must not grow forever."""
    path = str(tmp_path / "ttyH")
    async with SimController(path, config=SimConfig(instant=True, history=10)) as sim:
        _, writer = await serialx.open_serial_connection(url=path, baudrate=115200)
        try:
            await sim.wait_attached()
            for i in range(60):
                writer.write(f"G0 X{i}\n".encode())
            await sim.wait_received(b"G0 X59")
            assert len(sim.received) <= 20
            assert sim.received[-1].data == b"G0 X59"
            assert len(sim.sent) <= 20
        finally:
            writer.close()
