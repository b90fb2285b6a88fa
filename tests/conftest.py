"""The event loop every asyncio test runs on: the daemon's default (`[daemon] event_loop`).

`HOSTD_TEST_LOOP=asyncio` (or `uvloop`) runs the suite on the other one. Also a
fixture every transport's tests share: `rpc_answer_fails_once`.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import os
from collections.abc import Callable, Mapping
from typing import Any

import pytest
import uvloop

from hostd.api import rpc
from hostd.config import DaemonConfig

LOOPS: dict[str, Callable[[], asyncio.AbstractEventLoop]] = {
    "asyncio": asyncio.new_event_loop,
    "uvloop": uvloop.new_event_loop,
}


# The analysis workers (hostd/machine/workers.py) fork from multiprocessing's forkserver,
# one per test process: with the G-code readers loaded there once, a test's daemon gets
# a worker in milliseconds, not the second and a half of CPU of importing them again
# (hundreds of daemons start jobs in the suite). The workers' limits are unchanged.
multiprocessing.set_forkserver_preload(["hostd.machine.preflight"])


# The longest tests (tens of seconds of a simulated board's real time each), run first:
# pytest-xdist hands tests out in collection order, and one of these handed out last kept
# the whole suite waiting on a single worker while the others had nothing left to do.
LONGEST_FIRST = (
    "tests/stateful/",
    "tests/test_demo.py",
    "tests/daemon/test_resume_safety.py",
    "tests/daemon/test_process.py",
    "tests/fuzz/test_parser_fuzz.py",
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    def rank(item: pytest.Item) -> int:
        return next(
            (i for i, p in enumerate(LONGEST_FIRST) if item.nodeid.startswith(p)),
            len(LONGEST_FIRST),
        )

    items.sort(key=rank)  # stable: the rest keep their order


def chosen_loop() -> str:
    return os.environ.get("HOSTD_TEST_LOOP") or DaemonConfig().event_loop


def pytest_asyncio_loop_factories(
    config: pytest.Config, item: pytest.Item
) -> Mapping[str, Callable[[], asyncio.AbstractEventLoop]]:
    name = chosen_loop()
    return {name: LOOPS[name]}


@pytest.fixture
def rpc_answer_fails_once(monkeypatch: pytest.MonkeyPatch) -> Callable[[], None]:
    """Call it, and `rpc.answer` raises for the next message it is given (a bug past the
    dispatcher, which answers everything itself), then answers as always."""

    def arm() -> None:
        real = rpc.answer
        calls = 0

        async def answer(incoming: rpc.Incoming, methods: Any, context: object) -> bytes | None:
            nonlocal calls
            calls += 1
            if calls == 1:
                raise RuntimeError("a bug in rpc.answer")
            return await real(incoming, methods, context)

        monkeypatch.setattr(rpc, "answer", answer)

    return arm
