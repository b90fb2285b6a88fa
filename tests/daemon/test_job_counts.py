"""A job's `lines_acked` is what the board answered, never what was sent (issue 30 keeps it
so through every change to the job's path), both as the job is told and as its row is
kept on disk for a crash to find.

A board whose planner is full reads no more: the lines of the window it holds are sent
and not answered. The simulated g2core does this (its planner's room, hostd/sim), so
while long moves run the job must show fewer answered than sent.
"""

from __future__ import annotations

import asyncio
import sqlite3
from pathlib import Path

import pytest

from hostd.daemon import DB_NAME
from tests.daemon.conftest import running_daemon
from tests.daemon.test_api import job_end

pytestmark = pytest.mark.asyncio

LONG_MOVES = "G21 G90\n" + "G1 X300 F300\nG1 X0\n" * 40  # minutes on the board: it fills


def _row(db: Path, job_id: int) -> tuple[int, int]:
    with sqlite3.connect(db) as connection:
        found = connection.execute(
            "SELECT lines_sent, lines_acked FROM jobs WHERE id = ?", (job_id,)
        ).fetchone()
    return (int(found[0]), int(found[1])) if found else (0, 0)


async def test_lines_acked_stays_behind_lines_sent_while_the_board_holds_lines(
    tmp_path: Path,
) -> None:
    async with running_daemon(tmp_path) as hostd:
        rpc = await hostd.client()
        try:
            await hostd.idle(rpc)
            await rpc.call("subscribe", topics=["job"], machine="sim1")
            await rpc.call("file.upload", name="long.nc", data=LONG_MOVES)
            job_id = int((await rpc.call("job.start", machine="sim1", file="long.nc"))["job"])
            # Told: the board holds lines it read and has not answered (its planner full).
            held = await rpc.notification(
                lambda n: (
                    n["method"] == "job"
                    and n["params"]["job"]["id"] == job_id
                    and n["params"]["job"]["lines_sent"] > n["params"]["job"]["lines_acked"] > 0
                )
            )
            told = held["params"]["job"]
            assert told["state"] == "running"
            # Kept: the row on disk says no more than the board answered either (it is
            # written every second while the job runs: wait for one after the first).
            db = hostd.daemon.state_dir / DB_NAME
            async with asyncio.timeout(10):
                while True:
                    sent, acked = await asyncio.to_thread(_row, db, job_id)
                    if sent > acked > 0:
                        break
                    await asyncio.sleep(0.05)
            live = await rpc.call("job.get", job=job_id)
            assert live["lines_acked"] < live["lines_sent"]
            # Cancelled with the planner full: the line the board ran is still far behind
            # the last it answered, and the job's end keeps it so (a resume starts there;
            # only a completed job ran every line it answered).
            await rpc.call("job.cancel", machine="sim1")
            ended = await job_end(rpc, job_id)
            assert ended["state"] == "cancelled"
            assert isinstance(ended["line_executed"], int)
            assert ended["line_executed"] < ended["lines_acked"], ended
        finally:
            await rpc.close()
