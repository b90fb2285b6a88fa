"""The worker pool that reads whole files off the daemon's interpreter: its limits hold,
a worker past them is replaced, and the function's own errors come back as they are."""

from __future__ import annotations

import asyncio
import os

import pytest

from hostd.machine.workers import AnalysisLimit, WorkerPool

pytestmark = pytest.mark.asyncio

MEMORY = 1 << 30


def _allocate(size: int) -> int:
    return len(bytearray(size))


def _fail(text: str) -> None:
    raise ValueError(text)


def _pid() -> int:
    return os.getpid()


def _sleep_then_pid(seconds: float) -> int:
    import time

    time.sleep(seconds)
    return os.getpid()


async def test_past_the_memory_limit_is_a_clear_error_and_the_worker_is_replaced() -> None:
    pool = WorkerPool(memory=MEMORY)
    try:
        first = await pool.run("a test", _pid)
        with pytest.raises(AnalysisLimit) as over:
            await pool.run("reading big.gcode", _allocate, 2 * MEMORY)
        assert over.value.code == 1013
        assert over.value.data == {"limit": "memory", "bytes": MEMORY}
        assert "reading big.gcode needed more than 1024 MiB" in over.value.message
        assert await pool.run("a test", _allocate, 1 << 20) == 1 << 20
        assert await pool.run("a test", _pid) != first  # a new process
    finally:
        pool.close()


async def test_the_function_s_own_error_comes_back_and_the_worker_stays() -> None:
    pool = WorkerPool()
    try:
        first = await pool.run("a test", _pid)
        with pytest.raises(ValueError, match="line 3"):
            await pool.run("a test", _fail, "line 3")
        assert await pool.run("a test", _pid) == first
    finally:
        pool.close()


async def test_a_cancelled_request_kills_its_worker_and_close_refuses_the_rest() -> None:
    pool = WorkerPool(timeout=600)
    try:
        first = await pool.run("a test", _pid)
        task = asyncio.create_task(pool.run("a test", _sleep_then_pid, 600))
        await asyncio.sleep(0)  # the request is on its way to the worker
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        assert await pool.run("a test", _pid) != first
    finally:
        pool.close()
    with pytest.raises(AnalysisLimit, match="stopping"):
        await pool.run("a test", _pid)


async def test_a_prewarmed_worker_serves_the_first_request_and_no_other_starts() -> None:
    pool = WorkerPool()
    try:
        warming = asyncio.create_task(pool.prewarm(__name__))
        await asyncio.sleep(0)  # on its way: a request now waits for it, not for a second one
        first = await pool.run("a test", _pid)
        await warming
        [executor] = pool._all  # one process started in all
        assert first in {p.pid for p in executor._processes.values()}
        assert await pool.run("a test", _pid) == first
    finally:
        pool.close()


async def test_a_pool_closed_while_it_prewarms_keeps_no_worker() -> None:
    pool = WorkerPool()
    warming = asyncio.create_task(pool.prewarm(__name__))
    await asyncio.sleep(0)
    pool.close()
    await warming
    assert not pool._all and not pool._idle
    with pytest.raises(AnalysisLimit, match="stopping"):
        await pool.run("a test", _pid)
