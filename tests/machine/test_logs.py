"""Logs: one JSON object a line, the machine named, the serial traffic only at debug."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator

import pytest

from hostd.logs import configure_logging
from hostd.machine.stream import JobStream
from hostd.protocol.commands import Realtime
from hostd.protocol.states import MachineState as S
from tests.conftest import suite_logging
from tests.machine.conftest import Rig

pytestmark = pytest.mark.asyncio


@pytest.fixture
def debug_json(capsys: pytest.CaptureFixture[str]) -> Iterator[None]:
    """Configured before the rig is built: a bound logger keeps the config it was bound under."""
    configure_logging("debug", "json")
    yield
    suite_logging()


@pytest.fixture
def info_json(capsys: pytest.CaptureFixture[str]) -> Iterator[None]:
    configure_logging("info", "json")
    yield
    suite_logging()


def records(err: str) -> list[dict[str, object]]:
    return [json.loads(line) for line in err.splitlines() if line.strip()]


async def test_debug_json_logs_carry_the_machine_and_the_raw_traffic(
    capsys: pytest.CaptureFixture[str], debug_json: None, rig: Rig
) -> None:
    await rig.engine.send("G0 X2")
    logs = records(capsys.readouterr().err)
    traffic = [r for r in logs if r["event"] in ("tx", "rx")]
    assert any(r["event"] == "tx" and r["line"] == "b'G0 X2\\n'" for r in traffic), traffic
    assert any(r["event"] == "rx" for r in traffic)
    assert all(r["machine"] == "m1" and r["level"] == "debug" for r in traffic)
    assert all("timestamp" in r for r in logs)


async def test_at_info_the_traffic_is_not_logged(
    capsys: pytest.CaptureFixture[str], info_json: None, rig: Rig
) -> None:
    capsys.readouterr()
    await rig.engine.send("G0 X2")
    await rig.engine.send("{xvm:n}")
    logs = records(capsys.readouterr().err)
    assert not [r for r in logs if r["event"] in ("tx", "rx")]
    assert all(r["machine"] == "m1" for r in logs if "state" in r)


async def test_what_happens_during_a_job_is_logged_with_its_job(
    capsys: pytest.CaptureFixture[str], info_json: None, rig: Rig
) -> None:
    capsys.readouterr()
    stream = JobStream(iter([(1, "G1 X40 F3000"), (2, "G1 X0")]), job_id=7)
    rig.engine.start_stream(stream)
    async with asyncio.timeout(5):  # the engine itself has read that the board runs
        await rig.engine.wait_for(lambda: rig.engine.model.state is S.RUN)
    rig.engine.realtime(Realtime.JOB_KILL)
    async with asyncio.timeout(5):
        await stream.result
    logs = records(capsys.readouterr().err)
    states = [r for r in logs if r["event"] == "controller state" and r.get("job") == 7]
    assert states, logs
    assert all(r["machine"] == "m1" for r in states)
