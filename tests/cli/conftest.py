"""A real `hostd serve` subprocess per test module, and the `hostd` CLI run as subprocesses.

The daemon runs the built-in simulated board (`data_port = "sim"`); the
fixture waits for its socket to accept and for the machine to be idle, and
its teardown stops it with SIGTERM and checks that it exits 0. Waits are on
events (a connect that succeeds, a subscription's notifications) bounded
by deadlines, never bare sleeps.
"""

from __future__ import annotations

import asyncio
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import pytest

from hostd.cli.client import Client

MACHINE = "sim1"
# Bounds against a hang, not timing checks. On a loaded two-core machine (load average
# 12-16) `python -m hostd serve` took over 15 s to import and listen, and its exit
# on SIGTERM waits for the first analysis worker if that is still starting (the
# forkserver's imports; ProcessPoolExecutor.shutdown waits for a submit in progress):
# 9 s once, past the 10 s allowed with Python's own exit.
START_TIMEOUT = 45.0
STOP_TIMEOUT = 45.0
CLI_TIMEOUT = 30.0


@dataclass
class Daemon:
    """How to reach the daemon under test, and the CLI pointed at it."""

    socket: str
    env: dict[str, str]
    log: Path
    process: subprocess.Popen[bytes]

    def cli(self, *args: str, stdin: str | None = None) -> subprocess.CompletedProcess[str]:
        """`hostd ARGS...` to completion, output captured as text."""
        return subprocess.run(
            [sys.executable, "-m", "hostd", *args],
            env=self.env,
            input=stdin,
            stdin=None if stdin is not None else subprocess.DEVNULL,
            capture_output=True,
            text=True,
            timeout=CLI_TIMEOUT,
        )

    def spawn(self, *args: str) -> Spawned:
        """`hostd ARGS...` left running, to be talked to and interrupted."""
        return Spawned(
            subprocess.Popen(
                [sys.executable, "-m", "hostd", *args],
                env=self.env,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
        )

    def call(self, method: str, **params: Any) -> Any:
        """One API call from the test itself (to look, not to act)."""

        async def go() -> Any:
            async with Client(self.socket) as c:
                return await c.call(method, **params)

        return asyncio.run(go())

    def wait_machine(
        self, predicate: Callable[[dict[str, Any]], bool], timeout: float = 10.0
    ) -> dict[str, Any]:
        """The machine's snapshot once `predicate` holds, re-checked on each notification."""

        async def go() -> dict[str, Any]:
            async with Client(self.socket) as c:
                await c.call("subscribe", topics=["status", "supervisor", "job"], machine=MACHINE)
                notes = c.notifications()
                async with asyncio.timeout(timeout):
                    while True:
                        snap: dict[str, Any] = await c.call("machine.status", machine=MACHINE)
                        if predicate(snap):
                            return snap
                        await notes.__anext__()

        try:
            return asyncio.run(go())
        except TimeoutError:
            snap = self.call("machine.status", machine=MACHINE)
            raise AssertionError(
                f"machine never got there; now: {snap}\n{self.log_tail()}"
            ) from None

    def wait_idle(self) -> dict[str, Any]:
        return self.wait_machine(lambda s: s["supervisor"] == "idle")

    def log_tail(self, lines: int = 30) -> str:
        text = self.log.read_text(errors="replace").splitlines()
        return "daemon log:\n" + "\n".join(text[-lines:])


class Spawned:
    """A running CLI whose output lines can be waited for as they come.

    One thread per output pipe moves lines into a queue, so a test can wait
    for a given line with a deadline instead of blocking on a pipe forever.
    """

    def __init__(self, process: subprocess.Popen[str]) -> None:
        self.process = process
        self.lines: queue.Queue[tuple[str, str]] = queue.Queue()
        self.seen: list[tuple[str, str]] = []
        self._pumps = [
            threading.Thread(target=self._pump, args=(name, pipe), daemon=True)
            for name, pipe in (("out", process.stdout), ("err", process.stderr))
        ]
        for pump in self._pumps:
            pump.start()

    def _pump(self, name: str, pipe: IO[str] | None) -> None:
        assert pipe is not None
        for line in pipe:
            self.lines.put((name, line.rstrip("\n")))

    def expect(self, text: str, stream: str = "err", timeout: float = 10.0) -> str:
        """The first line (from now on) of `stream` that contains `text`."""
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            try:
                name, line = self.lines.get(timeout=max(left, 0.0))
            except queue.Empty:
                self.process.kill()
                raise AssertionError(f"no {stream} line with {text!r}; saw {self.seen}") from None
            self.seen.append((name, line))
            if name == stream and text in line:
                return line

    def answer(self, line: str) -> None:
        assert self.process.stdin is not None
        self.process.stdin.write(line + "\n")
        self.process.stdin.flush()

    def interrupt(self) -> None:
        self.process.send_signal(signal.SIGINT)

    def finish(self, timeout: float = 20.0) -> tuple[int, str, str]:
        """Exit status and the output not yet taken by `expect`, once the CLI has exited."""
        try:
            status = self.process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
            raise AssertionError(f"the CLI did not exit; saw {self.seen}") from None
        for pump in self._pumps:
            pump.join(timeout=5)
        rest: dict[str, list[str]] = {"out": [], "err": []}
        while not self.lines.empty():
            name, line = self.lines.get_nowait()
            self.seen.append((name, line))
            rest[name].append(line)
        return status, "\n".join(rest["out"]), "\n".join(rest["err"])


def _accepting(path: str) -> bool:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        try:
            probe.connect(path)
        except OSError:
            return False
        return True


def _write_config(root: Path, extra: str = "") -> Path:
    config = root / "hostd.toml"
    config.write_text(
        f"""
[daemon]
socket = "{root / "hostd.sock"}"
state_dir = "{root / "state"}"

[[machines]]
id = "{MACHINE}"
data_port = "sim"
auto_connect = true
{extra}""",
        encoding="utf-8",
    )
    return config


@pytest.fixture(scope="module")
def daemon(
    tmp_path_factory: pytest.TempPathFactory, request: pytest.FixtureRequest
) -> Iterator[Daemon]:
    """`EXTRA_CONFIG` in a test module: more TOML after the machine (another machine)."""
    root = tmp_path_factory.mktemp("cli")
    config = _write_config(root, getattr(request.module, "EXTRA_CONFIG", ""))
    sock = str(root / "hostd.sock")
    env = {k: v for k, v in os.environ.items() if k not in ("FORCE_COLOR", "TTY_COMPATIBLE")}
    env.update(HOSTD_SOCKET=sock, NO_COLOR="1", COLUMNS="200")
    log = root / "daemon.log"
    with log.open("wb") as log_file:
        process = subprocess.Popen(
            [sys.executable, "-m", "hostd", "serve", "--config", str(config), "--socket", sock],
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=log_file,
            stderr=subprocess.STDOUT,
        )
    d = Daemon(sock, env, log, process)
    try:
        deadline = time.monotonic() + START_TIMEOUT
        while not _accepting(sock):
            assert process.poll() is None, (
                f"hostd serve exited {process.returncode}\n{d.log_tail()}"
            )
            assert time.monotonic() < deadline, f"socket never accepted\n{d.log_tail()}"
            time.sleep(0.05)
        d.wait_idle()
        yield d
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
        try:
            status = process.wait(timeout=STOP_TIMEOUT)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
            raise AssertionError(f"hostd serve ignored SIGTERM\n{d.log_tail()}") from None
    assert status == 0, f"hostd serve exited {status} on SIGTERM\n{d.log_tail()}"


@pytest.fixture
def idle(daemon: Daemon) -> Daemon:
    """The daemon, with the machine idle before the test begins (tests share the machine)."""
    daemon.wait_idle()
    return daemon
