"""Issue 24 through the real socket: reading a file never stalls the daemon, a file past
its limits is a clear error, and numbers no board reads are refused with their line."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from tests.daemon.conftest import Rpc, RpcFailure, Running, running_daemon

pytestmark = pytest.mark.asyncio

# The line that froze the daemon for 27 s (issue 24), at the start of a long file.
HOSTILE = "X111" * 16 + "#"


def _long_file(path: Path, lines: int) -> None:
    body = [HOSTILE, "G21 G90 G0 X0 Y0", "G1 Z-1 F300"]
    body += [f"G1 X{i % 300}.{i % 997:03d} Y{(i * 7) % 200}.5 F800" for i in range(lines)]
    body += [HOSTILE] * 1000
    path.write_text("\n".join(body) + "\n")


async def test_daemon_info_and_a_feedhold_answer_while_a_hostile_analysis_runs(
    hostd: Running, rpc: Rpc
) -> None:
    _long_file(hostd.jobs / "huge.gcode", 60_000)
    other = await hostd.client()
    try:
        analysis = asyncio.create_task(rpc.call("file.analyze", file="huge.gcode"))
        # Another connection is answered while the analysis is still under way: the
        # analysis runs on a worker process, and the loop never waits on it.
        for _ in range(5):
            info = await other.call("daemon.info")
            assert "version" in info
            assert not analysis.done()
        await other.call("machine.feedhold", machine="sim1")
        await other.call("machine.cycle_start", machine="sim1")
        assert not analysis.done()
        result = await analysis
        assert result["lines"] == 60_000 + 1003
        hostile = [w for w in result["warning_details"] if w["line"] == 1]
        assert hostile and hostile[0]["count"] == 1001
    finally:
        await other.close()


async def test_an_analysis_past_its_time_limit_is_refused_and_the_next_one_runs(
    tmp_path: Path,
) -> None:
    async with running_daemon(tmp_path, daemon={"analysis_timeout": 1.0}) as hostd:
        rpc = await hostd.client()
        try:
            _long_file(hostd.jobs / "huge.gcode", 600_000)  # well past 1 s of analysis
            (hostd.jobs / "small.gcode").write_text("G0 X1\nG1 X2 F100\n")
            with pytest.raises(RpcFailure) as over:
                await rpc.call("file.analyze", file="huge.gcode")
            assert over.value.code == 1013
            assert over.value.data == {"limit": "time", "seconds": 1.0}
            assert "longer than 1 s" in over.value.message
            info = await rpc.call("daemon.info")  # the daemon goes on
            assert "version" in info
            small = await rpc.call("file.analyze", file="small.gcode")  # on a fresh worker
            assert small["lines"] == 2 and small["feeds"] == 1
        finally:
            await rpc.close()


async def test_a_number_no_board_reads_is_refused_with_its_line(hostd: Running, rpc: Rpc) -> None:
    big = "G21 G90\nG0 X1 Y1\nG1 X2 F" + "9" * 400 + "\nG1 X3\nG1 X4\n"
    (hostd.jobs / "big.gcode").write_text(big)
    (hostd.jobs / "nan.gcode").write_text("G21\nG0 X1\nG0 X2\nG1 Y2 Fnan\nG1 X3\n")
    for name, line, reason in (("big.gcode", 3, "integer digits"), ("nan.gcode", 4, "nan")):
        with pytest.raises(RpcFailure) as refused:
            await rpc.call("file.analyze", file=name)
        assert refused.value.code == 1012, refused.value.message
        assert refused.value.data["line"] == line
        assert reason in refused.value.data["reason"]
        assert f"line {line}" in refused.value.message
        with pytest.raises(RpcFailure) as plan:
            await rpc.call("job.recovery", machine="sim1", file=name, line=5)
        assert plan.value.code == 1012 and plan.value.data["line"] == line
        # Before: the resume's preamble carried `Finf` to the board. Now nothing starts.
        with pytest.raises(RpcFailure) as start:
            await rpc.call("job.start", machine="sim1", file=name, start_line=5)
        assert start.value.code == 1012 and start.value.data["line"] == line
    assert await rpc.call("job.list", machine="sim1") == []
    assert (await rpc.call("machine.status", machine="sim1"))["supervisor"] == "idle"


async def test_a_four_hundred_digit_number_in_a_line_is_no_internal_error(
    hostd: Running, rpc: Rpc
) -> None:
    for text in ("N" + "1" * 400 + " G0 X1", "G0 X1 T" + "7" * 400, "G10 L2 P" + "1" * 400):
        (hostd.jobs / "n.gcode").write_text(f"G21\n{text}\n")
        with pytest.raises(RpcFailure) as refused:
            await rpc.call("file.analyze", file="n.gcode")
        assert refused.value.code == 1012 and refused.value.data["line"] == 2


async def test_the_first_analysis_finds_its_worker_already_started(tmp_path: Path) -> None:
    """`[daemon] prewarm_workers` (the default): a worker starts with the daemon."""
    async with running_daemon(tmp_path, daemon={"prewarm_workers": True}) as hostd:
        pool = hostd.daemon.workers
        async with asyncio.timeout(60):
            await pool.warmed()
        [warm] = pool._idle  # nothing asked for it: it was started with the daemon
        rpc = await hostd.client()
        try:
            (hostd.jobs / "small.gcode").write_text("G0 X1\nG1 X2 F100\n")
            assert (await rpc.call("file.analyze", file="small.gcode"))["lines"] == 2
        finally:
            await rpc.close()
        assert pool._idle == [warm] and pool._all == {warm}  # that one served it
