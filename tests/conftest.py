"""The event loop every asyncio test runs on: the daemon's default (`[daemon] event_loop`).

`HOSTD_TEST_LOOP=asyncio` (or `uvloop`) runs the suite on the other one.
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import Callable, Mapping

import pytest
import uvloop

from hostd.config import DaemonConfig

LOOPS: dict[str, Callable[[], asyncio.AbstractEventLoop]] = {
    "asyncio": asyncio.new_event_loop,
    "uvloop": uvloop.new_event_loop,
}


def chosen_loop() -> str:
    return os.environ.get("HOSTD_TEST_LOOP") or DaemonConfig().event_loop


def pytest_asyncio_loop_factories(
    config: pytest.Config, item: pytest.Item
) -> Mapping[str, Callable[[], asyncio.AbstractEventLoop]]:
    name = chosen_loop()
    return {name: LOOPS[name]}
