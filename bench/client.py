"""The bench's side of the daemon: a blocking JSON-RPC client and the daemon as a process.

Blocking on purpose: the bench measures the daemon, and a plain socket with
one `sendall` per request keeps the client's own cost small and its
timestamps honest (taken right before the bytes are written).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections import deque
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

CLK_TCK = os.sysconf("SC_CLK_TCK")
UPLOAD_CHUNK = 512 * 1024  # bytes of G-code per file.upload request (the line limit is 1 MiB)


class RpcFailure(Exception):
    def __init__(self, error: dict[str, Any]) -> None:
        super().__init__(f"{error.get('code')}: {error.get('message')}")
        self.code: int = error.get("code", 0)
        self.error = error


class Client:
    """One connection. Answers are matched by id; notifications are kept in order."""

    def __init__(self, path: str, timeout: float = 30.0) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.settimeout(timeout)
        self.sock.connect(path)
        self._ids = itertools.count(1)
        self._buf = b""
        self._answers: dict[int, dict[str, Any]] = {}
        self.notifications: deque[dict[str, Any]] = deque()

    def close(self) -> None:
        self.sock.close()

    def request(self, method: str, **params: Any) -> tuple[int, bytes]:
        msg_id = next(self._ids)
        message: dict[str, Any] = {"jsonrpc": "2.0", "id": msg_id, "method": method}
        if params:
            message["params"] = params
        return msg_id, json.dumps(message, separators=(",", ":")).encode() + b"\n"

    def send(self, data: bytes) -> None:
        self.sock.sendall(data)

    def answer(self, msg_id: int) -> Any:
        while msg_id not in self._answers:
            self._read_more()
        msg = self._answers.pop(msg_id)
        if "error" in msg:
            raise RpcFailure(msg["error"])
        return msg["result"]

    def call(self, method: str, **params: Any) -> Any:
        msg_id, data = self.request(method, **params)
        self.send(data)
        return self.answer(msg_id)

    def notification(self, predicate: Callable[[dict[str, Any]], bool], timeout: float) -> Any:
        deadline = time.monotonic() + timeout
        while True:
            while self.notifications:
                msg = self.notifications.popleft()
                if predicate(msg):
                    return msg
            if time.monotonic() > deadline:
                raise TimeoutError("no such notification")
            self._read_more()

    def _read_more(self) -> None:
        chunk = self.sock.recv(1 << 20)
        if not chunk:
            raise ConnectionError("the daemon closed the connection")
        self._buf += chunk
        *lines, self._buf = self._buf.split(b"\n")
        for line in lines:
            if not line:
                continue
            msg = json.loads(line)
            if "id" in msg and msg.get("method") is None:
                self._answers[msg["id"]] = msg
            else:
                self.notifications.append(msg)

    # helpers for the daemon's methods

    def upload(self, name: str, data: str, chunk: int = UPLOAD_CHUNK) -> None:
        """A file in chunks: hidden until the final one, each after the first naming
        the upload the first opened and its byte offset (docs/api.md, Uploads)."""
        parts = [data[i : i + chunk] for i in range(0, len(data), chunk)] or [""]
        more: dict[str, Any] = {}
        for i, part in enumerate(parts):
            final = i == len(parts) - 1
            answer = self.call("file.upload", name=name, data=part, final=final, **more)
            if not final:
                more = {"upload": answer["upload"], "offset": answer["size"]}

    def wait_job_end(self, job_id: int, timeout: float) -> dict[str, Any]:
        """Until a `job` notification says the job ended (subscribe to `job` first)."""
        note = self.notification(
            lambda n: (
                n.get("method") == "job"
                and n["params"]["job"]["id"] == job_id
                and n["params"]["job"]["state"] not in ("running", "paused")
            ),
            timeout,
        )
        job: dict[str, Any] = note["params"]["job"]
        return job


def program(lines: int) -> str:
    """A G-code file of `lines` short moves, all different, as a CAM program's would be."""
    return "".join(f"G1 X{i % 3000 / 10:.3f} Y{i % 700 / 10:.3f} F3000\n" for i in range(lines))


def run_delay(pid: int) -> tuple[float, int]:
    """(seconds the process's main thread waited on a run queue, its time slices) so far.

    /proc/PID/schedstat: time on the CPU, time runnable but waiting for one, slices.
    The wait is what a busy machine adds to every wake-up: the daemon's event loop
    and the controllers are each one main thread.
    """
    _, waited, slices = Path(f"/proc/{pid}/schedstat").read_text().split()[:3]
    return int(waited) / 1e9, int(slices)


def raster(lines: int) -> str:
    """A laser's raster: short `G1` moves along X, the power changing on each, as a photo's.

    0.1 mm pixels at 6,000 mm/min are 1,000 moves a second; the board's rate
    is set by the bench's controller (bench/planner.py), not by the feed.
    """
    head = "G1 X0 F6000 S0\n"
    return head + "".join(
        f"G1 X{(i % 1000) / 10 if (i // 1000) % 2 == 0 else 100 - (i % 1000) / 10:.1f} "
        f"S{(i * 37) % 1000}\n"
        for i in range(1, lines)
    )


class DaemonProcess:
    """`python -m hostd.service` with a config of one machine on `data_port`.

    `also` adds further machines (id -> data port), configured like the first;
    `machine` (the first) stays the one the helpers ask about by default.
    """

    def __init__(
        self,
        workdir: Path,
        data_port: str,
        *,
        machine: str = "bench",
        also: Mapping[str, str] | None = None,
        window: int = 4,
        log_level: str = "info",
        extra: str = "",
        tables: str = "",
        event_loop: str = "uvloop",
        cpus: set[int] | None = None,
        module: str = "hostd.service",
        dialects: Mapping[str, str] | None = None,
    ) -> None:
        self.workdir = workdir
        self.machine = machine
        self.machines = {machine: data_port, **(also or {})}
        self.socket = str(workdir / "hostd.sock")
        self.config = workdir / "hostd.toml"
        self.config.write_text(
            "[daemon]\n"
            f'socket = "{self.socket}"\n'
            f'state_dir = "{workdir / "state"}"\n'
            f'log_level = "{log_level}"\n'
            f'event_loop = "{event_loop}"\n'
            + tables  # further top-level tables ([mqtt], [web]), before the machines
            + "".join(
                _machine_table(id_, port, (dialects or {}).get(id_, "g2core"), window) + extra
                for id_, port in self.machines.items()
            )
        )
        self.log = workdir / "hostd.log"
        self.cpus = cpus
        self.module = module  # another entry point (a patched daemon) for experiments
        self.proc: subprocess.Popen[bytes] | None = None
        self.pid = 0

    def start(self, timeout: float = 20.0) -> None:
        command = [sys.executable, "-m", self.module, "--config", str(self.config)]
        with self.log.open("ab") as log:
            self.proc = subprocess.Popen(
                [*command, "--log-format", "json"],
                stdout=subprocess.DEVNULL,
                stderr=log,
                preexec_fn=self._pin if self.cpus else None,
            )
        self.pid = self.proc.pid
        deadline = time.monotonic() + timeout
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(f"daemon exited {self.proc.returncode}; see {self.log}")
            try:
                with contextlib.closing(Client(self.socket)) as client:
                    if all(
                        client.call("machine.status", machine=m)["supervisor"] == "idle"
                        for m in self.machines
                    ):
                        break
            except (OSError, ConnectionError, RpcFailure):
                pass
            if time.monotonic() > deadline:
                raise TimeoutError(f"daemon not idle within {timeout} s; see {self.log}")
            time.sleep(0.05)

    def _pin(self) -> None:
        """In the child, before exec: every thread the daemon starts inherits it."""
        assert self.cpus is not None
        os.sched_setaffinity(0, self.cpus)

    def client(self) -> Client:
        return Client(self.socket)

    def wait_idle(self, timeout: float = 10.0, machine: str | None = None) -> None:
        deadline = time.monotonic() + timeout
        machine = machine or self.machine
        with contextlib.closing(self.client()) as client:
            while client.call("machine.status", machine=machine)["supervisor"] != "idle":
                if time.monotonic() > deadline:
                    raise TimeoutError("machine not idle")
                time.sleep(0.02)

    def cpu_seconds(self) -> float:
        return sum(self.cpu_times())

    def cpu_times(self) -> tuple[float, float]:
        """CPU seconds in the process itself and in the kernel for it (utime, stime)."""
        fields = Path(f"/proc/{self.pid}/stat").read_text().rsplit(")", 1)[1].split()
        return int(fields[11]) / CLK_TCK, int(fields[12]) / CLK_TCK

    def status_kb(self, key: str) -> int:
        for line in Path(f"/proc/{self.pid}/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1])
        raise KeyError(key)

    def reset_peak(self) -> None:
        """Reset VmHWM to the current RSS (clear_refs 5), to measure one phase's peak."""
        Path(f"/proc/{self.pid}/clear_refs").write_text("5")

    def fds(self) -> int:
        return len(os.listdir(f"/proc/{self.pid}/fd"))

    def stop(self, timeout: float = 20.0) -> int | None:
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


def _machine_table(machine: str, port: str, dialect: str, window: int) -> str:
    """A `[[machines]]` table; `window` is g2core's key alone (grbl counts characters,
    and the config refuses a key of another dialect)."""
    table = f'\n[[machines]]\nid = "{machine}"\ndata_port = "{port}"\ndialect = "{dialect}"\n'
    return table + (f"window = {window}\n" if dialect == "g2core" else "")
