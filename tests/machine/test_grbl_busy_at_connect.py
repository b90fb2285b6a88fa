"""A grbl board found busy at connect, over a real pty: the simulated grblHAL.

The board of a daemon that died, or whose link went, mid-job still runs the
moves in its 1,024-byte receive buffer and its planner. It answers `?`, but
reads no line until they end (docs/dialects.md, "A board busy at connect").
After an operation of ours was cut off (`ran_unwatched`) it is stopped at
once, before the handshake can finish; a board busy with moves no operation
of ours sent is left to end them, and the machine connects then.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from hostd.machine.events import ExceptionRaised
from hostd.machine.supervisor import State as Sup
from hostd.protocol.errors import MachineError, NotConnected
from hostd.sim.grbl import GrblConfig
from tests.machine.test_grbl import GrblBench, grbl_bench

pytestmark = pytest.mark.asyncio

# 0.5 mm moves at F3000: 10 ms each. The board's buffer and planner hold some 160 of
# them (1.6 s), more than the handshake's 2 s timeout leaves of a 300-line job.
BOARD = GrblConfig(flavour="grblhal", speed_factor=1.0, feedhold_decel=0.02)
END_X = 150.0
JOB = "G21 G90 M3 S800\n" + "".join(f"G1 X{i * 0.5:.1f} F3000\n" for i in range(1, 301))


async def buffer_full(bench: GrblBench) -> None:
    """Until the board holds a full receive buffer of the job's lines, and runs."""
    engine = bench.machine.engine

    def full() -> bool:
        board = bench.board.board
        return board.state == "Run" and board.rx_free < 100

    async with asyncio.timeout(10):
        await engine.wait_for(full)


def told(bench: GrblBench, words: str) -> bool:
    return any(
        isinstance(e, ExceptionRaised) and words in str(e.report.get("msg"))
        for e in bench.recorder.events
    )


async def test_a_board_left_running_by_a_lost_link_is_stopped_before_the_handshake_ends(
    tmp_path: Path,
) -> None:
    async with grbl_bench(tmp_path, BOARD, startup_motion=True) as bench:
        bench.write("raster.nc", JOB)
        job = await bench.machine.start_make("raster.nc")
        await buffer_full(bench)
        await bench.machine.disconnect()  # the link goes mid-job: the board runs on
        row = await bench.job_ended(job.id)
        assert row.state == "interrupted"
        assert bench.board.state == "Run"
        sent = len(bench.recorder.tx())
        with pytest.raises(NotConnected, match="busy with moves it was given before"):
            await bench.machine.connect()  # answered at once, not when the board is through
        await bench.supervisor(Sup.IDLE)
        tx = bench.recorder.tx()[sent:]
        assert tx.index("!") < tx.index("\x18")  # held, then reset at rest
        assert told(bench, "busy with moves it was given before")
        board = bench.board.board
        assert board.state == "Idle" and board.beam_power() == 0.0
        # Stopped where it was found, not at the job's end 1.6 s of moves later.
        assert bench.board.position["x"] < END_X - 10
        assert bench.machine.engine.session.rx_size == 1024  # the build was read


async def test_without_startup_motion_it_is_held_until_the_operator_resets_it(
    tmp_path: Path,
) -> None:
    async with grbl_bench(tmp_path, BOARD) as bench:  # startup_motion = false
        bench.write("raster.nc", JOB)
        await bench.machine.start_make("raster.nc")
        await buffer_full(bench)
        await bench.machine.disconnect()
        sent = len(bench.recorder.tx())
        with pytest.raises(NotConnected, match="busy with moves"):
            await bench.machine.connect()
        await bench.recorder.wait_for(
            lambda e: isinstance(e, ExceptionRaised) and "not read yet" in str(e.report)
        )
        assert "\x18" not in bench.recorder.tx()[sent:]  # its startup blocks are unread
        engine = bench.machine.engine
        async with asyncio.timeout(5):  # its reports, polled while it holds
            await engine.wait_for(lambda: engine.model.board_state == "Hold:0")
        assert bench.board.state == "Hold:0"
        assert bench.machine.supervisor.state is Sup.DISCONNECTED
        occupied = bench.machine.snapshot()["occupied"]  # what the dashboard shows
        assert occupied["state"] == "Hold" and "held instead of reset" in occupied["message"]
        await bench.machine.reset()  # the operator's: the board drops what it held
        await bench.supervisor(Sup.IDLE)
        assert bench.board.state == "Idle"
        assert bench.board.position["x"] < END_X - 10
        assert bench.machine.snapshot()["occupied"] is None


async def test_moves_no_operation_of_ours_sent_are_left_to_end_and_it_connects_then(
    tmp_path: Path,
) -> None:
    async with grbl_bench(tmp_path, BOARD) as bench:
        engine = bench.machine.engine
        lines = [asyncio.ensure_future(engine.send(line)) for line in JOB.splitlines()]
        await buffer_full(bench)
        await bench.machine.disconnect()  # the operator's lines: no operation was running
        outcomes = await asyncio.gather(*lines, return_exceptions=True)
        assert any(isinstance(o, MachineError) for o in outcomes)  # cut off by the close
        sent = len(bench.recorder.tx())
        with pytest.raises(NotConnected, match="Run, busy with moves"):
            await bench.machine.connect()
        assert bench.board.state == "Run"
        await bench.supervisor(Sup.IDLE)
        assert "!" not in bench.recorder.tx()[sent:] and "\x18" not in bench.recorder.tx()[sent:]
        # It ran every line it had read, as a board its host let go of does.
        written = [t for t in bench.recorder.tx()[:sent] if t.startswith("G1 X")]
        assert bench.board.position["x"] == pytest.approx(float(written[-1].split()[1][1:]))
