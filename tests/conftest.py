"""The event loop every asyncio test runs on: the daemon's default (`[daemon] event_loop`).

`HOSTD_TEST_LOOP=asyncio` (or `uvloop`) runs the suite on the other one. Also a
fixture every transport's tests share: `rpc_answer_fails_once`.
"""

from __future__ import annotations

import asyncio
import compileall
import importlib.util
import logging
import multiprocessing
import os
import re
import sys
from collections.abc import Callable, Mapping
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import pytest
import structlog
import uvloop
from hypothesis import settings
from xdist.scheduler import LoadScopeScheduling

try:  # pytest's own rewriting, private: the warm-up below is skipped if it moved
    from _pytest.assertion import rewrite
except ImportError:  # pragma: no cover - another pytest
    rewrite = None  # type: ignore[assignment]

from hostd.api import rpc
from hostd.config import DaemonConfig

LOOPS: dict[str, Callable[[], asyncio.AbstractEventLoop]] = {
    "asyncio": asyncio.new_event_loop,
    "uvloop": uvloop.new_event_loop,
}


# Hypothesis' default deadline (200 ms an example) is a timing assertion: on a loaded
# two-core machine one example of tests/protocol/test_per_line_paths.py took 472 ms and
# failed a correct test. The examples are bounded by their count, not by the clock.
settings.register_profile("hostd", deadline=None)
settings.load_profile("hostd")


# The daemons, machines and boards the tests build in their own process log as `hostd
# serve` does by default (`[daemon] log_level = "info"`), not at structlog's default of
# everything: each debug line was rendered for the console, timestamped, written, captured
# and carried in the test's report to the xdist controller (about 36 kB a test in
# tests/daemon), some 14 % of those tests' CPU (docs/testing.md, "Third round").
# Info, warnings and errors still show with a failure; HOSTD_TEST_LOG_LEVEL=debug shows
# the rest. `structlog.testing.capture_logs` sees the same events (none asserted is debug).
LOG_LEVEL = logging.getLevelNamesMapping()[os.environ.get("HOSTD_TEST_LOG_LEVEL", "info").upper()]


def suite_logging() -> None:
    """The suite's logging, set for the session and again by a test that changed it."""
    structlog.reset_defaults()
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(LOG_LEVEL))


def pytest_configure(config: pytest.Config) -> None:
    suite_logging()


# The analysis workers (hostd/machine/workers.py) fork from multiprocessing's forkserver,
# one per test process: with the G-code readers loaded there once, a test's daemon gets
# a worker in milliseconds, not the second and a half of CPU of importing them again
# (hundreds of daemons start jobs in the suite). The workers' limits are unchanged.
multiprocessing.set_forkserver_preload(["hostd.machine.preflight"])


# The bytecode the workers would each write, written once first. On a clean clone
# (CI) every xdist worker rewrote the asserts of all the test modules itself as it
# collected (5.5 s of CPU a worker, 4 at once on two cores) and compiled hostd again:
# the controller writes those caches before it starts the workers, with pytest's own
# rewriting and in pytest's own format (a hash-checked pyc: a stale one is never used),
# on two processes. With the caches there it only reads each file's hash (0.2 s). Only
# where `make unit` lets bytecode be written; skipped where pytest would rewrite
# differently (the assertion-pass hook) or its rewriting functions moved (a cache
# only: the workers then write it as before). docs/testing.md, "Fourth round".
ROOT = Path(__file__).resolve().parents[1]
_REWRITTEN = re.compile(r"(^|/)(test_[^/]*|conftest)\.py$")


def _rewritten_pyc(source: Path) -> Path:
    return rewrite.get_cache_dir(source) / (source.name[:-3] + rewrite.PYC_TAIL)


def _rewrite_once(path: str) -> None:
    source = Path(path)
    pyc = _rewritten_pyc(source)
    source_hash, code = rewrite._rewrite_test(source, None)  # type: ignore[arg-type]
    pyc.parent.mkdir(exist_ok=True)
    partial = f"{pyc}.{os.getpid()}"
    with open(partial, "wb") as out:
        rewrite._write_pyc_fp(out, source_hash, code)
    os.replace(partial, pyc)  # atomic, as pytest's own: a worker reads it whole or not


def _compile_once(path: str) -> None:
    compileall.compile_file(path, quiet=2)


def _fresh(source: Path) -> bool:
    """A module's own pyc is there and newer than it (import checks it exactly)."""
    try:
        pyc = Path(importlib.util.cache_from_source(str(source)))
        return pyc.stat().st_mtime >= source.stat().st_mtime
    except OSError:
        return False


def warm_bytecode(config: pytest.Config) -> None:
    workers = getattr(config.option, "numprocesses", None)
    if (
        not workers
        or hasattr(config, "workerinput")
        or sys.dont_write_bytecode
        or config.getoption("assertmode") != "rewrite"
        or config.getini("enable_assertion_pass_hook")
        or rewrite is None
        or not all(
            hasattr(rewrite, name)
            for name in ("get_cache_dir", "PYC_TAIL", "_read_pyc", "_rewrite_test", "_write_pyc_fp")
        )
    ):
        return
    tests = sorted((ROOT / "tests").rglob("*.py"))
    rewritten = [
        str(p)
        for p in tests
        if _REWRITTEN.search(str(p)) and rewrite._read_pyc(p, _rewritten_pyc(p)) is None
    ]
    plain = [
        str(p)
        for p in [
            *(p for p in tests if not _REWRITTEN.search(str(p))),
            *(ROOT / "hostd").rglob("*.py"),
        ]
        if not _fresh(p)
    ]
    if not rewritten and not plain:
        return
    try:
        with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("fork")) as pool:
            list(pool.map(_rewrite_once, rewritten, chunksize=8))
            list(pool.map(_compile_once, plain, chunksize=16))
    except Exception as exc:  # only a cache: the workers write their own, as before
        config.issue_config_time_warning(
            pytest.PytestWarning(f"bytecode warm-up skipped: {exc!r}"), stacklevel=2
        )


def pytest_sessionstart(session: pytest.Session) -> None:
    warm_bytecode(session.config)  # before pytest-xdist starts the workers (its own is trylast)


# The longest tests (tens of seconds of a simulated board's real time each), run first:
# pytest-xdist hands tests out in collection order, and one of these handed out last kept
# the whole suite waiting on a single worker while the others had nothing left to do.
# Handed out one at a time (`pytest_xdist_make_scheduler`), so that each goes to the
# next free worker.
LONGEST_FIRST = (
    "tests/stateful/",
    "tests/daemon/test_process.py",
    "tests/test_demo.py",
    "tests/web/test_operator.py",
    "tests/web/",
    "tests/daemon/test_resume_safety.py",
    "tests/fuzz/",
    "tests/test_layers.py",
    "tests/mqtt/test_process.py",
)

# Each module here starts its own `hostd serve` for all its tests (tests/cli/conftest.py,
# module-scoped `daemon`), or reads what its tests share once (tests/test_layers.py parses
# all of hostd): its tests go to one worker, which does it once. rs274's reference runs
# (test_gcodestate_rs274.py, `runs`) are made once per test run under a file lock: handed
# out one at a time, its 16 tests went to every worker, and all but the one making the
# runs sat idle on the lock for their 4-5 s (the slowest setups of the suite after the
# browser tests': 5.4 s and 3.8 s in one run).
ONE_WORKER_PER_MODULE = (
    "tests/cli/",
    "tests/test_layers.py",
    "tests/protocol/test_gcodestate_rs274.py",
)


# Long tests that mostly wait (a simulated board's motion in real time: about a tenth of
# a core each), handed out among the chromium tests (a browser and a daemon each: most of
# a core) rather than after them. After them, the workers ran browser tests together,
# more than two cores' worth, and then the waiting tests together on idle cores. Those
# two sets at `-n 2`, back to back, twice: 144 s and 148 s of wall before, 117 s and
# 120 s spread (the browser tests' own walls 145-150 s before, 88-95 s spread).
WAIT_AMONG_BROWSERS = ("tests/daemon/test_resume_safety.py",)
BROWSERS = (
    "tests/web/test_operator.py",
    "tests/web/test_browser.py",
    "tests/web/test_operator_day.py",
)


def _spread(busy: list[pytest.Item], waiting: list[pytest.Item]) -> list[pytest.Item]:
    """`waiting` spaced evenly through `busy`, each list in its own order."""
    merged: list[pytest.Item] = []
    taken = 0
    for i, item in enumerate(busy):
        merged.append(item)
        while taken < len(waiting) * (i + 1) // len(busy):
            merged.append(waiting[taken])
            taken += 1
    return merged + waiting[taken:]


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    def rank(item: pytest.Item) -> int:
        return next(
            (i for i, p in enumerate(LONGEST_FIRST) if item.nodeid.startswith(p)),
            len(LONGEST_FIRST),
        )

    items.sort(key=rank)  # stable: the rest keep their order
    waiting = [item for item in items if item.nodeid.startswith(WAIT_AMONG_BROWSERS)]
    busy = [item for item in items if item.nodeid.startswith(BROWSERS)]
    if waiting and busy:  # where the browser tests begin
        moved = {item.nodeid for item in [*waiting, *busy]}
        before = [item for item in items[: items.index(busy[0])] if item.nodeid not in moved]
        after = [item for item in items if item.nodeid not in moved][len(before) :]
        items[:] = [*before, *_spread(busy, waiting), *after]


class OneAtATime(LoadScopeScheduling):
    """pytest-xdist's `--dist load` (the default), one test at a time, in collection order.

    `load` gave each worker its first quarter of the tests in one block: LONGEST_FIRST
    all went to the first worker, which ran them one after another (400 s of the whole
    run's 450 at load average 7; docs/testing.md, "The suite's own time"). Here a
    worker holds up to three units (a test; a module of ONE_WORKER_PER_MODULE) and takes
    the next as it finishes one. Kept in collection order: not reordered by size.
    """

    def __init__(self, config: pytest.Config, log: Any = None) -> None:
        super().__init__(config, log)
        config.option.loadscopereorder = False
        self._indices: dict[Any, dict[str, int]] = {}

    def _split_scope(self, nodeid: str) -> str:
        if nodeid.startswith(ONE_WORKER_PER_MODULE):
            return nodeid.partition("::")[0]
        return nodeid

    # LoadScopeScheduling keeps every unit a worker has finished in `assigned_work` and
    # sums them all again on every report (`_pending_of`, from `mark_test_complete`,
    # `tests_finished` and `has_pending`), and finds each test's index with `list.index`:
    # both grow with the tests run, quadratic over the suite's ~3,200 one-test units.
    # A finished unit is dropped (the pending counts are the same without it) and the
    # indices are looked up in a dict (docs/testing.md, "Third round").

    def mark_test_complete(self, node: Any, item_index: int, duration: float = 0) -> None:
        nodeid = self.registered_collections[node][item_index]
        units = self.assigned_work[node]
        scope = self._split_scope(nodeid)
        unit = units[scope]
        unit[nodeid] = True
        if all(unit.values()):
            del units[scope]
        self._reschedule(node)

    def _assign_work_unit(self, node: Any) -> None:
        scope, unit = self.workqueue.popitem(last=False)
        self.assigned_work.setdefault(node, {})[scope] = unit
        index = self._indices.get(node)
        if index is None:
            collection = self.registered_collections[node]
            index = self._indices[node] = {nodeid: i for i, nodeid in enumerate(collection)}
        node.send_runtest_some([index[nodeid] for nodeid, done in unit.items() if not done])


def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """`OneAtATime` in place of the default `--dist load`; another `--dist` stays as asked."""
    if config.getvalue("dist") != "load":
        return None
    return OneAtATime(config, log)


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
