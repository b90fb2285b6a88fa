"""The bench's helper processes: controllers, subscriber fleet, flooder, web client."""

from __future__ import annotations

import json
import subprocess
import sys
from typing import Any


class ControllerProcess:
    """bench/instant_controller.py, driven through its stdin/stdout."""

    def __init__(
        self,
        link: str,
        dialect: str = "g2core",
        *,
        rate: float = 0.0,
        blocks: int | None = None,
        fifo: bool = False,
    ) -> None:
        self.link = link
        self.dialect = dialect
        args = ["--link", link, "--dialect", dialect, "--rate", str(rate)]
        if blocks is not None:
            args += ["--blocks", str(blocks)]
        if fifo:
            args.append("--fifo")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "bench.instant_controller", *args],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        self._expect_line("listening")

    @property
    def pid(self) -> int:
        return self.proc.pid

    def _send(self, command: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def _readline(self) -> str:
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError("the instant controller exited")
        return line.strip()

    def _expect_line(self, want: str) -> None:
        line = self._readline()
        if line != want:
            raise RuntimeError(f"instant controller said {line!r}, expected {want!r}")

    def expect(self, lines: int) -> None:
        self._send(f"expect {lines}")

    def status_reports(self, count: int, rate: float) -> None:
        self._send(f"sr {count} {rate}")

    def dump(self) -> dict[str, Any]:
        """What was recorded since the last dump (`opened` notices are skipped)."""
        self._send("dump")
        while True:
            line = self._readline()
            if line.startswith("{"):
                result: dict[str, Any] = json.loads(line)
                return result

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                self._send("quit")
                self.proc.wait(5)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait()


class _Helper:
    """A helper process (`python -m module args`) that prints `ready`, runs until it reads
    `stop` on stdin, then prints its result as one JSON line."""

    def __init__(self, module: str, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", module, *args],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline().strip()
        if line != "ready":
            self.kill()
            raise RuntimeError(f"{module} did not start: {line!r}")

    def stop(self) -> dict[str, Any]:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write("stop\n")
        self.proc.stdin.flush()
        result: dict[str, Any] = json.loads(self.proc.stdout.readline())
        self.proc.wait(10)
        return result

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


class SubscriberFleet(_Helper):
    """bench/subscribers.py: `count` clients subscribed to `topics`, read continuously."""

    def __init__(self, socket: str, count: int, topics: str, machine: str | None) -> None:
        super().__init__(
            "bench.subscribers",
            *("--socket", socket, "--count", str(count)),
            *("--topics", topics, "--machine", machine or ""),
        )


class Flooder(_Helper):
    """bench/flood.py: one client keeping `outstanding` `machine.send` queries unanswered."""

    def __init__(self, socket: str, machine: str, outstanding: int = 200, batch: int = 10) -> None:
        super().__init__(
            "bench.flood",
            *("--socket", socket, "--machine", machine),
            *("--outstanding", str(outstanding), "--batch", str(batch)),
        )


class WebClient(_Helper):
    """bench/webclient.py: the dashboard's WebSocket, logged in with a token, read continuously."""

    def __init__(self, url: str, token: str) -> None:
        super().__init__("bench.webclient", "--url", url, "--token", token)
