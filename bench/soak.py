"""`make soak`: the long versions of the fault tests, against the daemon as a process.

    python -m bench.soak [--cycles 20] [--rounds 10] [--quick]

Machines are simulated (`data_port = "sim"`), so the daemon owns both ends.

1. Kill and restart: `--cycles` times, start the daemon on the same state
   directory, check the job the last one was killed in (`interrupted`, error
   1002, `lines_acked <= lines_sent < lines_total`, at most 100 lines or 1 s
   of progress behind what a client saw), start a job, SIGKILL the daemon
   mid-job. The stale socket it leaves must not stop the next start.
2. A subscriber that never reads: jobs run with and without a client that
   subscribed to everything and stopped reading; the other client sees
   every job complete, about as fast, and the stuck one is disconnected.
3. Growth: `--rounds` times in one daemon, 20 clients subscribe and leave,
   a job runs to completion and one is cancelled; the daemon's open fds and
   RSS are taken after each round and must not grow.

Prints a summary; exits 1 on any failure.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import socket
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bench.client import Client, DaemonProcess, RpcFailure

MACHINE = "sim1"
KILL_PROGRAM_LINES = 20_000
SOAK_JOB_LINES = 1_500
PERSIST_LINES = 100  # the daemon persists progress at most 100 lines or 1 s apart


def program(lines: int) -> str:
    """Short moves, so that the simulated board (ten times faster than real) keeps up."""
    return "".join(f"G1 X{i % 20 / 10:.2f} Y{i % 7 / 10:.2f} F6000\n" for i in range(lines))


@dataclass
class Report:
    failures: list[str] = field(default_factory=list)
    lines: list[str] = field(default_factory=list)

    def check(self, ok: bool, what: str) -> bool:
        if not ok:
            self.failures.append(what)
            print(f"  FAIL: {what}", flush=True)
        return ok

    def say(self, text: str) -> None:
        self.lines.append(text)
        print(text, flush=True)


DAEMON_MODULE = ["hostd.service"]  # --daemon-module: a patched daemon, for experiments


def sim_daemon(workdir: Path) -> DaemonProcess:
    return DaemonProcess(
        workdir,
        "sim",
        machine=MACHINE,
        extra="status_interval = 0.1\n",
        log_level="info",
        module=DAEMON_MODULE[0],
    )


def rss_kb(daemon: DaemonProcess) -> int:
    return daemon.status_kb("VmRSS")


def settled_fds(daemon: DaemonProcess) -> int:
    """Open fds, leaving out one that comes and goes (a worker thread's, SQLite's)."""
    counts = []
    for _ in range(5):
        counts.append(daemon.fds())
        time.sleep(0.05)
    return min(counts)


def acked_at_least(job_id: int, lines: int) -> Callable[[dict[str, Any]], bool]:
    """A predicate: a `job` notification of this job with at least `lines` acked."""

    def match(note: dict[str, Any]) -> bool:
        job = note.get("params", {}).get("job", {})
        return bool(note.get("method") == "job" and job.get("id") == job_id) and (
            job["lines_acked"] >= lines
        )

    return match


def wait_for(predicate: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(what)
        time.sleep(0.02)


# --- 1. SIGKILL and restart mid-job ----------------------------------------------------------


def kill_restart(workdir: Path, cycles: int, report: Report) -> None:
    report.say(f"== kill and restart mid-job, {cycles} cycles")
    daemon = sim_daemon(workdir)
    previous: tuple[int, int, float] | None = None  # job id, lines_acked seen, lines/s
    starts, lags, fds, rss = [], [], [], []
    db = workdir / "state" / "hostd.db"
    for cycle in range(1, cycles + 1):
        t0 = time.monotonic()
        try:
            daemon.start(timeout=30)
        except (RuntimeError, TimeoutError) as exc:
            report.check(False, f"cycle {cycle}: the daemon did not come back: {exc}")
            return
        starts.append(time.monotonic() - t0)
        client = daemon.client()
        try:
            if previous is not None:
                job_id, seen, rate = previous
                row = client.call("job.get", job=job_id)
                ok = report.check(
                    row["state"] == "interrupted" and (row["error"] or {}).get("code") == 1002,
                    f"cycle {cycle}: job {job_id} is {row['state']} ({row['error']}), "
                    "not interrupted/1002",
                )
                ok &= report.check(
                    row["lines_acked"] <= row["lines_sent"] < KILL_PROGRAM_LINES,
                    f"cycle {cycle}: job {job_id} acked {row['lines_acked']} > sent "
                    f"{row['lines_sent']} (or all sent)",
                )
                lags.append(seen - row["lines_acked"])
                # Persisted at most 100 lines or 1 s apart (the runner looks every 0.1 s).
                allowed = max(PERSIST_LINES, rate * 1.0) + rate * 0.2
                if ok:
                    report.check(
                        seen - row["lines_acked"] <= allowed,
                        f"cycle {cycle}: persisted {row['lines_acked']} lines, a client had "
                        f"seen {seen} ({rate:.0f} lines/s)",
                    )
            if cycle == 1:
                client.upload("kill.gcode", program(KILL_PROGRAM_LINES))
            client.call("subscribe", topics=["job"], machine=MACHINE)
            started = time.monotonic()
            job_id = client.call("job.start", machine=MACHINE, file="kill.gcode")["job"]
            # Run a while: a different point in the job every cycle.
            target = 100 + (cycle * 37) % 400
            note = client.notification(acked_at_least(job_id, target), timeout=60)
            seen = note["params"]["job"]["lines_acked"]
            fds.append(daemon.fds())
            rss.append(rss_kb(daemon))
            previous = (job_id, seen, seen / (time.monotonic() - started))
        except (RpcFailure, TimeoutError, OSError, ConnectionError) as exc:
            report.check(False, f"cycle {cycle}: {type(exc).__name__}: {exc}")
            daemon.kill()
            return
        finally:
            client.close()
        daemon.kill()
        report.check(os.path.exists(daemon.socket), f"cycle {cycle}: SIGKILL left no stale socket?")
    # The last kill: one more start to check it, then a clean stop.
    daemon.start(timeout=30)
    with contextlib.closing(daemon.client()) as client:
        assert previous is not None
        row = client.call("job.get", job=previous[0])
        report.check(row["state"] == "interrupted", f"last job is {row['state']}")
        report.check(row["lines_acked"] <= row["lines_sent"], "last job acked > sent")
    code = daemon.stop()
    report.check(code == 0, f"SIGTERM after the soak: exit {code}")
    report.check(not os.path.exists(daemon.socket), "socket left after a clean stop")
    report.say(
        f"  start to idle: median {statistics.median(starts):.2f} s, max {max(starts):.2f} s; "
        f"persisted progress behind what a client saw: max {max(lags, default=0)} lines"
    )
    report.say(
        f"  per fresh daemon mid-job: fds {min(fds)}..{max(fds)}, RSS "
        f"{min(rss) / 1024:.1f}..{max(rss) / 1024:.1f} MiB; job db {db.stat().st_size} bytes"
    )
    report.check(max(fds) - min(fds) <= 2, f"fds of a fresh daemon vary: {fds}")


# --- 2. a subscriber that never reads -------------------------------------------------------


def stuck_subscriber(workdir: Path, jobs: int, report: Report) -> None:
    report.say(f"== a subscriber that never reads, {jobs} jobs with and without it")
    daemon = sim_daemon(workdir)
    daemon.start()
    stuck: socket.socket | None = None
    try:
        with contextlib.closing(daemon.client()) as client:
            client.upload("soak.gcode", program(SOAK_JOB_LINES))
            client.call("subscribe", topics=["job"], machine=MACHINE)
            base = [_timed_job(daemon, client) for _ in range(jobs)]
            fds_before = daemon.fds()
            stuck = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            stuck.connect(daemon.socket)
            request = {
                "jsonrpc": "2.0",
                "id": 1,
                "method": "subscribe",
                "params": {"topics": ["status", "job", "console", "supervisor"]},
            }
            stuck.sendall(json.dumps(request).encode() + b"\n")
            with_stuck = [_timed_job(daemon, client) for _ in range(jobs)]
            other_ok = client.call("daemon.info")["api"] == 1
        disconnected = _closed_by_peer(stuck)
        log = daemon.log.read_text()
        report.check(other_ok, "the other client stopped being answered")
        report.check(disconnected, "the stuck subscriber was never disconnected")
        report.check(
            "api client not reading; disconnected" in log or "write did not drain" in log,
            "no log line about disconnecting the stuck subscriber",
        )
        slow = statistics.median(with_stuck) / statistics.median(base)
        report.say(
            f"  job of {SOAK_JOB_LINES} lines: median {statistics.median(base):.2f} s without, "
            f"{statistics.median(with_stuck):.2f} s with a stuck subscriber ({slow:.2f}x); "
            f"stuck one disconnected: {disconnected}"
        )
        report.check(slow < 1.5, f"jobs {slow:.2f}x slower with a stuck subscriber")
        wait_for(lambda: daemon.fds() <= fds_before, 5, "fds after the stuck client left")
    except (RpcFailure, TimeoutError, OSError, ConnectionError) as exc:
        report.check(False, f"stuck subscriber: {type(exc).__name__}: {exc}")
    finally:
        if stuck is not None:
            stuck.close()
        daemon.stop()


def _timed_job(daemon: DaemonProcess, client: Client) -> float:
    daemon.wait_idle(timeout=30)
    t0 = time.monotonic()
    job_id = client.call("job.start", machine=MACHINE, file="soak.gcode")["job"]
    job = client.wait_job_end(job_id, timeout=120)
    if job["state"] != "completed" or job["lines_acked"] != job["lines_total"]:
        raise RuntimeError(f"job {job_id} ended {job['state']} at {job['lines_acked']}")
    return time.monotonic() - t0


def _closed_by_peer(sock: socket.socket) -> bool:
    """Drain what was delivered before the daemon closed us; True if it did close."""
    sock.settimeout(5)
    try:
        while sock.recv(1 << 20):
            pass
    except (ConnectionResetError, BrokenPipeError):
        return True
    except TimeoutError:
        return False
    return True


# --- 3. growth over rounds ------------------------------------------------------------------


def growth(workdir: Path, rounds: int, report: Report) -> None:
    report.say(f"== fds and RSS over {rounds} rounds of clients, a job and a cancel")
    daemon = sim_daemon(workdir)
    daemon.start()
    fds, rss = [], []
    try:
        with contextlib.closing(daemon.client()) as client:
            client.upload("soak.gcode", program(SOAK_JOB_LINES))
            client.upload("long.gcode", program(KILL_PROGRAM_LINES))
            client.call("subscribe", topics=["job"], machine=MACHINE)
            for _ in range(rounds):
                visitors = []
                for _ in range(20):
                    visitor = daemon.client()
                    visitor.call("subscribe", topics=["status", "job", "supervisor"])
                    visitors.append(visitor)
                _timed_job(daemon, client)
                daemon.wait_idle(timeout=30)
                job_id = client.call("job.start", machine=MACHINE, file="long.gcode")["job"]
                client.notification(acked_at_least(job_id, 50), timeout=30)
                cancelled = client.call("job.cancel", machine=MACHINE)
                report.check(cancelled["state"] == "cancelled", f"cancel: {cancelled['state']}")
                for visitor in visitors:
                    visitor.close()
                time.sleep(0.3)  # the daemon notices the visitors left
                daemon.wait_idle(timeout=30)
                fds.append(settled_fds(daemon))
                rss.append(rss_kb(daemon))
    except (RpcFailure, TimeoutError, OSError, ConnectionError, RuntimeError) as exc:
        report.check(False, f"growth: {type(exc).__name__}: {exc}")
        return
    finally:
        daemon.stop()
    report.say(f"  fds after each round: {fds}")
    report.say(f"  RSS after each round (MiB): {[round(r / 1024, 1) for r in rss]}")
    settled = rss[len(rss) // 2 :]  # after warm-up (caches, the allocator's arenas)
    report.check(fds[-1] <= fds[0], f"fds grew: {fds}")
    report.check(
        settled[-1] - settled[0] < 2048,
        f"RSS grew {(settled[-1] - settled[0]) / 1024:.1f} MiB over the second half",
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m bench.soak", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--cycles", type=int, default=20, help="kill/restart cycles")
    parser.add_argument("--rounds", type=int, default=10, help="growth rounds")
    parser.add_argument("--jobs", type=int, default=3, help="jobs with and without a stuck client")
    parser.add_argument("--quick", action="store_true", help="3 cycles, 3 rounds, 2 jobs")
    parser.add_argument("--keep", action="store_true", help="keep the work directory")
    parser.add_argument("--only", help="comma-separated subset: kill,stuck,growth")
    parser.add_argument("--daemon-module", default="hostd.service", help="the daemon's module")
    args = parser.parse_args(argv)
    DAEMON_MODULE[0] = args.daemon_module
    if args.quick:
        args.cycles, args.rounds, args.jobs = 3, 3, 2
    workdir = Path(tempfile.mkdtemp(prefix="hostd-soak-"))
    report = Report()
    t0 = time.monotonic()
    steps: list[tuple[str, Callable[[Path], None]]] = [
        ("kill", lambda d: kill_restart(d, args.cycles, report)),
        ("stuck", lambda d: stuck_subscriber(d, args.jobs, report)),
        ("growth", lambda d: growth(d, args.rounds, report)),
    ]
    for name, step in steps:
        if args.only and name not in args.only.split(","):
            continue
        where = workdir / name
        where.mkdir()
        try:
            step(where)
        except Exception as exc:  # a harness failure is a soak failure too
            report.check(False, f"{name}: {type(exc).__name__}: {exc}")
    verdict = "PASS" if not report.failures else f"FAIL ({len(report.failures)})"
    print(f"\nsoak: {verdict} in {time.monotonic() - t0:.0f} s")
    for failure in report.failures:
        print(f"  - {failure}")
    if args.keep or report.failures:
        print(f"work directory kept: {workdir}")
    else:
        shutil.rmtree(workdir, ignore_errors=True)
    return 1 if report.failures else 0


if __name__ == "__main__":
    sys.exit(main())
