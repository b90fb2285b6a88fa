"""`hostd serve` processes and one broker: the last will on SIGKILL, a fleet under one prefix."""

from __future__ import annotations

import signal
from pathlib import Path

import pytest

from tests.daemon.test_process import daemon_process, ready_client
from tests.mqtt.conftest import Broker, decoded, watching

pytestmark = pytest.mark.asyncio


def write_config(directory: Path, broker: Broker, prefix: str) -> Path:
    directory.mkdir(exist_ok=True)
    lines = [
        "[daemon]",
        f'socket = "{directory / "hostd.sock"}"',
        f'state_dir = "{directory / "state"}"',
        "",
        "[[machines]]",
        'id = "sim1"',
        'data_port = "sim"',
        "status_interval = 0.1",
        "",
        "[mqtt]",
        f'url = "{broker.url}"',
        f'topic_prefix = "{prefix}"',
        f'client_id = "hostd-{prefix.replace("/", "-")}"',
        "reconnect_min = 0.1",
    ]
    path = directory / "hostd.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


async def test_sigkill_leaves_the_last_will_offline(tmp_path: Path, broker: Broker) -> None:
    config = write_config(tmp_path / "a", broker, "shop/a")
    async with (
        watching(broker, "shop/a/online") as watcher,
        daemon_process(tmp_path / "a", config) as process,
    ):
        await watcher.state("shop/a/online", lambda p: p == "online")
        process.proc.send_signal(signal.SIGKILL)
        await process.proc.wait()
        message = await watcher.next(lambda m: str(m.topic) == "shop/a/online")
        assert decoded(message) == "offline" and message.retain


async def test_a_subscriber_sees_the_fleet_of_two_daemons_under_one_prefix(
    tmp_path: Path, broker: Broker
) -> None:
    configs = {name: write_config(tmp_path / name, broker, f"fleet/{name}") for name in "ab"}
    async with (
        daemon_process(tmp_path / "a", configs["a"]) as a,
        daemon_process(tmp_path / "b", configs["b"]) as b,
    ):
        for process in (a, b):
            rpc = await ready_client(process)  # sim1 idle on both
            await rpc.close()
        async with watching(broker, "fleet/#") as watcher:
            want = {f"fleet/{n}/{t}" for n in "ab" for t in ("online", "sim1/status")}
            kept = await watcher.retained(*want)
        for name in "ab":
            assert decoded(kept[f"fleet/{name}/online"]) == "online"
            status = decoded(kept[f"fleet/{name}/sim1/status"])
            assert status["machine"] == "sim1"
            assert status["snapshot"]["id"] == "sim1"
        # A clean stop says `offline` itself.
        a.proc.send_signal(signal.SIGTERM)
        assert await a.proc.wait() == 0
        async with watching(broker, "fleet/a/online") as watcher:
            assert await watcher.state("fleet/a/online") == "offline"
