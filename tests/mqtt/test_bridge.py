"""The bridge against a real mosquitto: retained state during a job, a broker restart, commands."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest

from tests.daemon.conftest import Rpc
from tests.mqtt.conftest import Bridged, Broker, bridged, decoded, program, watching

pytestmark = pytest.mark.asyncio

RETAINED = ("online", "sim1/status", "sim1/job", "sim1/faults")


async def start_job(rpc: Rpc, lines: int, step: float = 1.0) -> int:
    await rpc.call("file.upload", name="job.gcode", data=program(lines, step))
    await rpc.call("subscribe", topics=["job"], machine="sim1")
    started = await rpc.call("job.start", machine="sim1", file="job.gcode")
    job_id: int = started["job"]
    return job_id


async def acked(rpc: Rpc, job_id: int, at_least: int) -> dict[str, Any]:
    note = await rpc.notification(
        lambda n: (
            n["params"]["job"]["id"] == job_id and n["params"]["job"]["lines_acked"] >= at_least
        )
    )
    job: dict[str, Any] = note["params"]["job"]
    return job


async def streaming(b: Bridged, at_least: int = 20) -> tuple[Rpc, int]:
    """A client of the bridged daemon, and a long job it started that is under way."""
    rpc = await b.running.client()
    await b.running.idle(rpc)
    job_id = await start_job(rpc, 20_000)
    await acked(rpc, job_id, at_least)
    return rpc, job_id


async def ended(rpc: Rpc, job_id: int) -> dict[str, Any]:
    note = await rpc.notification(
        lambda n: (
            n["params"]["job"]["id"] == job_id
            and n["params"]["job"]["state"] not in ("running", "paused")
        )
    )
    job: dict[str, Any] = note["params"]["job"]
    return job


def running(job_id: int) -> Any:
    return lambda p: p["job"]["id"] == job_id and p["job"]["state"] == "running"


async def test_status_and_job_are_retained_while_a_job_runs_and_at_its_end(
    tmp_path: Path, broker: Broker
) -> None:
    async with bridged(tmp_path, broker) as b:
        rpc, job_id = await streaming(b, 50)
        # A subscriber arriving mid-job is told the state at once, by retained messages.
        async with watching(broker, "test/h1/#") as late:
            kept = await late.retained(*(f"test/h1/{t}" for t in RETAINED))
            assert kept["test/h1/online"].payload == b"online"
            assert decoded(kept["test/h1/sim1/job"])["job"]["state"] == "running"
            assert not any(f["active"] for f in decoded(kept["test/h1/sim1/faults"])["faults"])
            # Live updates follow: the job topic is the API's `job` notification's params.
            live = await late.state("test/h1/sim1/job", lambda p: p["job"]["lines_acked"] > 100)
            assert live["machine"] == "sim1" and live["job"]["id"] == job_id
            snapshot = await late.state(
                "test/h1/sim1/status", lambda p: p["snapshot"]["supervisor"] == "operation"
            )
            assert snapshot["machine"] == "sim1"
            assert snapshot["snapshot"]["job"]["id"] == job_id
        await rpc.call("job.cancel", machine="sim1")
        # At its end: the retained job is the ended one.
        async with watching(broker, "test/h1/sim1/job") as after:
            final = await after.state(
                "test/h1/sim1/job", lambda p: p["job"]["state"] == "cancelled"
            )
            assert final["job"]["id"] == job_id
        await rpc.close()


async def test_a_broker_restart_mid_job_leaves_the_job_alone_and_state_is_republished(
    tmp_path: Path, broker: Broker
) -> None:
    async with bridged(tmp_path, broker) as b:
        rpc = await b.running.client()
        await b.running.idle(rpc)
        async with asyncio.timeout(15):
            await b.bridge.connected.wait()
        job_id = await start_job(rpc, 2_000, 0.5)
        before = await acked(rpc, job_id, 20)
        await broker.stop()
        async with asyncio.timeout(15):
            await b.bridge.disconnected.wait()
        # The job goes on while the broker is away, and the outbox does not grow.
        during = await acked(rpc, job_id, before["lines_acked"] + 200)
        assert during["state"] == "running"
        assert len(b.bridge.outbox) <= 10
        await broker.start()
        async with watching(broker, "test/h1/#") as watcher:
            # The restarted broker kept nothing (no persistence): this is the daemon again.
            kept = await watcher.retained(*(f"test/h1/{t}" for t in RETAINED))
            assert kept["test/h1/online"].payload == b"online"
            done = await ended(rpc, job_id)
            assert done["state"] == "completed"
            assert done["lines_acked"] == done["lines_total"] == 2_000
            final = await watcher.state(
                "test/h1/sim1/job", lambda p: p["job"]["state"] == "completed"
            )
            assert final["job"]["id"] == job_id
        assert b.bridge.connections == 2
        await rpc.close()


async def test_commands_are_refused_when_off(tmp_path: Path, broker: Broker) -> None:
    async with bridged(tmp_path, broker) as b:
        rpc, job_id = await streaming(b)
        async with watching(broker, "test/h1/online") as caller:
            answer = await caller.request("test/h1/sim1/cmd/job.cancel", {})
        assert answer["error"]["code"] == -32601
        assert "commands are off" in answer["error"]["message"]
        job = await rpc.call("job.get", job=job_id)
        assert job["state"] == "running"
        await rpc.call("job.cancel", machine="sim1")
        await rpc.close()


async def test_allowed_commands_run_when_on_and_others_are_refused(
    tmp_path: Path, broker: Broker
) -> None:
    async with bridged(tmp_path, broker, commands=True) as b:
        rpc, job_id = await streaming(b)
        async with watching(broker, "test/h1/online") as caller:
            refused = await caller.request("test/h1/sim1/cmd/machine.reset", {}, b"r1")
            assert refused["error"]["code"] == -32601
            assert "job.cancel" in refused["error"]["data"]["allowed"]
            # The payload is the params and nothing else: no way to name another method.
            smuggled = b'{}, "method": "machine.reset"'
            odd = await caller.request("test/h1/sim1/cmd/job.cancel", smuggled, b"s1")
            assert odd["error"]["code"] == -32700
            listed = await caller.request("test/h1/sim1/cmd/job.cancel", [1], b"l1")
            assert listed["error"]["code"] == -32602
            assert (await rpc.call("job.get", job=job_id))["state"] == "running"
            wrong = await caller.request("test/h1/sim1/cmd/job.cancel", {"machine": "x"}, b"w1")
            assert wrong["error"]["code"] == -32602
            answer = await caller.request("test/h1/sim1/cmd/job.cancel", {}, b"c1")
        assert answer["result"]["id"] == job_id
        assert answer["result"]["state"] == "cancelled"
        await rpc.close()
