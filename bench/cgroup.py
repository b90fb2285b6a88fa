"""A CPU cgroup of the bench's own: a fraction of one core for the daemon (P8).

cgroup v1 (`cpu.cfs_quota_us` / `cpu.cfs_period_us` in the `cpu` hierarchy)
or v2 (`cpu.max`), whichever this machine mounts; writing them needs root.
The bench makes a cgroup of its own, moves the daemon into it once it has
started and been given its file (`cgroup.procs` takes a process with all
its threads, and threads started later are born in it), and removes the
cgroup once the daemon has exited.

The period matters as much as the quota. CFS bandwidth control runs the
group at full speed until its quota for the period is spent, then not at
all until the period ends: at the kernel's default period (100 ms) a
quarter of a core is 75 ms stopped out of every 100, which no board's
buffer rides through and which is not what a slower CPU does (a Raspberry
Pi runs all the time, slower). A short period spreads the same budget
finely: at 10 ms the daemon is stopped at most 7.5 ms at a time.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

V1 = Path("/sys/fs/cgroup/cpu")
V2 = Path("/sys/fs/cgroup")


class CgroupUnavailable(Exception):
    """No writable CPU controller here (not root, or no cgroup mounted)."""


@dataclass
class CpuLimit:
    path: Path
    version: int
    quota_us: int
    period_us: int

    def stat(self) -> dict[str, int]:
        """cpu.stat: nr_periods, nr_throttled, throttled_time (ns, v1) / throttled_usec (v2)."""
        out: dict[str, int] = {}
        with contextlib.suppress(OSError):
            for line in (self.path / "cpu.stat").read_text().splitlines():
                key, _, value = line.partition(" ")
                if value.strip().isdigit():
                    out[key] = int(value)
        return out

    def enter(self, pid: int) -> None:
        """Move a process, every thread of it, into this cgroup."""
        (self.path / "cgroup.procs").write_text(str(pid))
        moved = (self.path / "cgroup.procs").read_text().split()
        threads = set(os.listdir(f"/proc/{pid}/task"))
        if self.version == 1:  # v1 lists threads in `tasks`: all of them must be here
            moved += (self.path / "tasks").read_text().split()
        if str(pid) not in moved or (self.version == 1 and not threads <= set(moved)):
            raise CgroupUnavailable(f"process {pid} did not move into {self.path} whole")

    def throttled_seconds(self) -> float:
        stat = self.stat()
        if "throttled_time" in stat:
            return stat["throttled_time"] / 1e9
        return stat.get("throttled_usec", 0) / 1e6

    def describe(self) -> str:
        share = self.quota_us / self.period_us
        return (
            f"cgroup v{self.version} {self.quota_us} us every {self.period_us} us "
            f"({share:.0%} of one core)"
        )


def _root() -> tuple[Path, int]:
    if (V1 / "cpu.cfs_quota_us").exists():
        return V1, 1
    if (V2 / "cgroup.controllers").exists() and "cpu" in (V2 / "cgroup.controllers").read_text():
        return V2, 2
    raise CgroupUnavailable("no cgroup cpu controller mounted (v1 cpu or v2 cpu.max)")


@contextlib.contextmanager
def cpu_limit(share: float, period_us: int) -> Iterator[CpuLimit]:
    """A fresh cgroup allowed `share` of one core, in periods of `period_us`; removed after."""
    root, version = _root()
    path = root / f"hostd-bench-{os.getpid()}"
    quota_us = max(1000, round(share * period_us))  # the kernel's least quota is 1 ms
    try:
        path.mkdir()
    except OSError as exc:
        raise CgroupUnavailable(f"cannot make {path}: {exc}") from exc
    try:
        if version == 1:
            (path / "cpu.cfs_period_us").write_text(str(period_us))
            (path / "cpu.cfs_quota_us").write_text(str(quota_us))
        else:
            (path / "cpu.max").write_text(f"{quota_us} {period_us}")
        yield CpuLimit(path, version, quota_us, period_us)
    finally:
        _remove(path)


def _remove(path: Path) -> None:
    """rmdir, once its processes are gone (a process that just exited may linger briefly)."""
    deadline = time.monotonic() + 5
    while True:
        try:
            path.rmdir()
            return
        except FileNotFoundError:
            return
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)
