"""The daemon as a process: systemd notify, SIGTERM, SIGKILL and restart, bad config."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import socket
import sys
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from tests.daemon.conftest import Rpc, RpcFailure, config_data

# Each test starts the daemon as a process, twice in some: its imports, its first worker
# and the job's file check take tens of seconds when the suite's longest tests all start
# together on two cores (a bound against a hang, not a timing check).
pytestmark = [pytest.mark.asyncio, pytest.mark.timeout(180)]
# A daemon's exit on SIGTERM, bounded against a hang: it took past 20 s once at load
# average 12 on two cores (docs/testing.md, "Flaky tests under load").
EXIT_WAIT = 45

SERVE = [sys.executable, "-m", "hostd.service"]


def write_config(tmp_path: Path, *daemon: str) -> Path:
    """`daemon`: more `[daemon]` lines."""
    data = config_data(tmp_path)
    lines = [
        "[daemon]",
        f'socket = "{data["daemon"]["socket"]}"',
        f'state_dir = "{data["daemon"]["state_dir"]}"',
        "analysis_nice = 0",  # the suite's processes keep the cores busy (conftest)
        *daemon,
        "",
        "[[machines]]",
        'id = "sim1"',
        'data_port = "sim"',
        "status_interval = 0.1",
    ]
    path = tmp_path / "hostd.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


@dataclass
class Process:
    proc: asyncio.subprocess.Process
    notify: socket.socket
    socket_path: str
    datagrams: asyncio.Queue[bytes] = field(default_factory=asyncio.Queue)

    async def read_notify(self) -> None:
        """Read every datagram as it comes, as systemd does. Left unread, Linux queues 10
        (net.unix.max_dgram_qlen): the watchdog's pings (5 a second here) fill that in
        two seconds, and the daemon's STOPPING=1 is then refused (EAGAIN) and lost."""
        loop = asyncio.get_running_loop()
        while True:
            self.datagrams.put_nowait(await loop.sock_recv(self.notify, 4096))

    async def message(self, want: bytes) -> list[bytes]:
        """Notify datagrams up to and including the one that contains `want`."""
        seen = []
        async with asyncio.timeout(60):  # a hang bound: see pytestmark
            while True:
                datagram = await self.datagrams.get()
                seen.append(datagram)
                if want in datagram:
                    return seen


@contextlib.asynccontextmanager
async def daemon_process(
    tmp_path: Path,
    config: Path,
    wrapper: tuple[str, ...] = (),
    env: dict[str, str] | None = None,
) -> AsyncIterator[Process]:
    """`hostd serve` with `config`; `wrapper` runs it (e.g. prlimit with its options);
    `env`: more environment."""
    notify_path = tmp_path / f"notify-{os.getpid()}-{len(os.listdir(tmp_path))}"
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(notify_path))
    notify.setblocking(False)
    env = {
        **os.environ,
        **(env or {}),
        "NOTIFY_SOCKET": str(notify_path),
        "WATCHDOG_USEC": "400000",
    }
    proc = await asyncio.create_subprocess_exec(
        *wrapper,
        *SERVE,
        "--config",
        str(config),
        "--log-format",
        "json",
        env=env,
        stdout=asyncio.subprocess.DEVNULL,
        stderr=asyncio.subprocess.PIPE,
    )
    process = Process(proc, notify, str(tmp_path / "hostd.sock"))
    reader = asyncio.create_task(process.read_notify())
    try:
        yield process
    finally:
        if proc.returncode is None:
            proc.kill()
        await proc.wait()
        reader.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await reader
        notify.close()


async def follow_until_acked(rpc: Rpc, job_id: int, lines: int) -> dict[str, object]:
    """The job's notification once `lines` are answered; a job that ended before fails the
    test at once, saying how (not 90 s later, as a timeout that hides it)."""
    note = await rpc.notification(
        lambda n: (
            n["method"] == "job"
            and n["params"]["job"]["id"] == job_id
            and (
                n["params"]["job"]["lines_acked"] >= lines
                or n["params"]["job"]["state"] not in ("running", "paused")
            )
        ),
        timeout=90,  # a daemon process just started: see pytestmark
    )
    job: dict[str, object] = note["params"]["job"]
    assert job["state"] in ("running", "paused"), job
    return job


async def start_long_job(rpc: Rpc) -> int:
    program = "".join(f"G1 X{i % 30} Y{i % 7} F3000\n" for i in range(20000))
    await rpc.call("file.upload", name="long.gcode", data=program)
    await rpc.call("subscribe", topics=["job"], machine="sim1")
    started = await rpc.call("job.start", machine="sim1", file="long.gcode")
    job_id: int = started["job"]
    return job_id


async def ready_client(process: Process) -> Rpc:
    seen = await process.message(b"READY=1")
    assert any(b"STATUS=" in d for d in seen)
    rpc = await Rpc.open(process.socket_path)
    # Subscribed before looking: a change between the look and the subscription is not missed.
    await rpc.call("subscribe", topics=["supervisor"], machine="sim1")
    async with asyncio.timeout(30):
        if (await rpc.call("machine.status", machine="sim1"))["supervisor"] != "idle":
            await rpc.notification(lambda n: n["params"].get("to") == "idle")
    return rpc


async def test_sigterm_mid_job_interrupts_it_and_removes_the_socket(tmp_path: Path) -> None:
    config = write_config(tmp_path)
    async with daemon_process(tmp_path, config) as process:
        rpc = await ready_client(process)
        assert oct(os.stat(process.socket_path).st_mode & 0o777) == oct(0o600)  # no group
        await process.message(b"WATCHDOG=1")
        job_id = await start_long_job(rpc)
        await follow_until_acked(rpc, job_id, 50)
        process.proc.send_signal(signal.SIGTERM)
        await process.message(b"STOPPING=1")
        async with asyncio.timeout(EXIT_WAIT):
            assert await process.proc.wait() == 0
            await rpc.ended()  # everything the daemon wrote has been read
        # A client that follows the job is told its end before the daemon goes, whatever
        # waited to be written with it (hostd/api/client.py, NOTICE_DELAY).
        told = [n["params"]["job"] for n in rpc.queued() if n["method"] == "job"]
        assert told and told[-1]["id"] == job_id and told[-1]["state"] == "interrupted", told[-3:]
        await rpc.close()
        assert not await asyncio.to_thread(os.path.exists, process.socket_path)

    async with daemon_process(tmp_path, config) as process:
        rpc = await ready_client(process)
        row = await rpc.call("job.get", job=job_id)
        assert row["state"] == "interrupted"
        assert 50 <= row["lines_acked"] <= row["lines_sent"] < 20000
        process.proc.send_signal(signal.SIGTERM)
        await rpc.close()
        async with asyncio.timeout(EXIT_WAIT):
            assert await process.proc.wait() == 0


# Put first on a daemon's PYTHONPATH: the analysis workers' forkserver, a new interpreter
# the daemon starts (`python -c "from multiprocessing.forkserver import main; ..."`),
# connects to HOSTD_TEST_HOLD's socket and waits there before its imports: a first
# worker's start that cannot end while the test holds it. The connection ends when the
# server does.
HOLD_FORKSERVER = """\
import os, socket, sys

if any("multiprocessing.forkserver import main" in arg for arg in sys.orig_argv):
    held = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    held.connect(os.environ["HOSTD_TEST_HOLD"])
    held.sendall(b"held")
    held.recv(1)  # until the test lets go
"""


@dataclass
class Held:
    env: dict[str, str]  # for the daemon: its forkserver is held
    started: asyncio.Future[None]  # the forkserver is running, held before its imports
    ended: asyncio.Future[None]  # and has exited


@contextlib.asynccontextmanager
async def held_forkserver(tmp_path: Path) -> AsyncIterator[Held]:
    site = tmp_path / "hold-site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(HOLD_FORKSERVER)
    loop = asyncio.get_running_loop()
    started: asyncio.Future[None] = loop.create_future()
    ended: asyncio.Future[None] = loop.create_future()
    writers: list[asyncio.StreamWriter] = []

    async def hold(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writers.append(writer)
        if await reader.readexactly(4) == b"held" and not started.done():
            started.set_result(None)
            await reader.read()  # its end: nothing more is sent
            ended.set_result(None)

    path = tmp_path / "hold.sock"
    server = await asyncio.start_unix_server(hold, str(path))
    python_path = os.pathsep.join(p for p in (str(site), os.environ.get("PYTHONPATH")) if p)
    env = {"PYTHONPATH": python_path, "HOSTD_TEST_HOLD": str(path)}
    try:
        yield Held(env, started, ended)
    finally:
        server.close()
        for writer in writers:
            writer.close()


async def test_sigterm_while_the_first_analysis_worker_starts_exits_at_once(
    tmp_path: Path,
) -> None:
    """The worker's start is a `submit` holding the executor's lock until the forkserver has
    done its imports; a stop then must neither block the loop on that lock nor wait for
    the imports on the way out (docs/testing.md, "Flaky tests under load")."""
    config = write_config(tmp_path)  # prewarm_workers: the default
    async with (
        held_forkserver(tmp_path) as forkserver,
        daemon_process(tmp_path, config, env=forkserver.env) as process,
    ):
        async with asyncio.timeout(60):  # a hang bound: see pytestmark
            await forkserver.started
        await process.message(b"READY=1")
        process.proc.send_signal(signal.SIGTERM)
        await process.message(b"STOPPING=1")
        # Held, the forkserver never forks the worker: before, the stop never ended.
        async with asyncio.timeout(EXIT_WAIT):
            assert await process.proc.wait() == 0
            # Killed by the daemon, not left to do its imports and fork a worker for nobody.
            await forkserver.ended
        assert not await asyncio.to_thread(os.path.exists, process.socket_path)
        assert process.proc.stderr is not None
        logs = [json.loads(line) for line in (await process.proc.stderr.read()).splitlines()]
        assert "hostd stopped" in [r["event"] for r in logs]


def descendants(pid: int) -> set[int]:
    """Every process below `pid` (its children, theirs, ...), read from /proc."""
    parents: dict[int, int] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rpartition(")")[2].split()
        except OSError:  # gone meanwhile
            continue
        parents[int(stat.parent.name)] = int(fields[1])
    found: set[int] = set()
    below = {pid}
    while below:
        below = {child for child, parent in parents.items() if parent in below} - found
        found |= below
    return found


def _settle(done: asyncio.Future[None]) -> None:
    if not done.done():
        done.set_result(None)


async def exited(pids: set[int]) -> None:
    """Until every process of `pids` has exited: a pidfd each turns readable then."""
    loop = asyncio.get_running_loop()
    waits: list[tuple[int, asyncio.Future[None]]] = []
    for pid in pids:
        try:
            fd = os.pidfd_open(pid)
        except ProcessLookupError:
            continue  # gone already
        done: asyncio.Future[None] = loop.create_future()
        loop.add_reader(fd, _settle, done)
        waits.append((fd, done))
    try:
        await asyncio.gather(*(done for _, done in waits))
    finally:
        for fd, _ in waits:
            loop.remove_reader(fd)
            os.close(fd)


async def test_sigkill_mid_job_then_restart_shows_it_interrupted(tmp_path: Path) -> None:
    config = write_config(tmp_path)
    async with daemon_process(tmp_path, config) as process:
        rpc = await ready_client(process)
        job_id = await start_long_job(rpc)
        seen = await follow_until_acked(rpc, job_id, 250)
        # Its analysis worker (the job's file was checked there), the forkserver it was
        # forked from, multiprocessing's resource tracker: none outlives the daemon.
        below = await asyncio.to_thread(descendants, process.proc.pid)
        assert len(below) >= 2, below
        process.proc.kill()
        await process.proc.wait()
        async with asyncio.timeout(EXIT_WAIT):  # a hang bound: before, they never exited
            await exited(below)
        await rpc.close()
        assert await asyncio.to_thread(os.path.exists, process.socket_path)  # left stale

    async with daemon_process(tmp_path, config) as process:
        rpc = await ready_client(process)  # the stale socket did not stop it
        row = await rpc.call("job.get", job=job_id)
        assert row["state"] == "interrupted"
        assert row["error"]["code"] == 1002
        # Persisted at most 100 lines or 1 s apart, and never more than was answered.
        assert 0 < row["lines_acked"] <= row["lines_sent"] < 20000
        assert row["lines_acked"] >= int(str(seen["lines_acked"])) - 100
        process.proc.send_signal(signal.SIGTERM)
        await rpc.close()
        async with asyncio.timeout(EXIT_WAIT):
            assert await process.proc.wait() == 0


async def test_sigkill_mid_upload_then_restart_publishes_nothing(tmp_path: Path) -> None:
    config = write_config(tmp_path, "jobs_quota = 1000000", "upload_expiry = 600")
    jobs = tmp_path / "state" / "jobs"
    async with daemon_process(tmp_path, config) as process:
        rpc = await ready_client(process)
        await rpc.call("file.upload", name="part.gcode", data="old\n")
        first = await rpc.call("file.upload", name="part.gcode", data="G0 X1\n", final=False)
        upload = first["upload"]
        await rpc.call("file.upload", name="part.gcode", data="G0 X2\n", upload=upload, offset=6)
        again = await rpc.call("file.upload", name="part.gcode", data="new\n", final=False)
        process.proc.kill()
        await process.proc.wait()
        await rpc.close()
        assert os.listdir(jobs / ".staging") == [again["upload"]]

    async with daemon_process(tmp_path, config) as process:
        rpc = await ready_client(process)
        assert os.listdir(jobs / ".staging") == []  # removed at start-up
        with pytest.raises(RpcFailure) as gone:
            await rpc.call(
                "file.upload", name="part.gcode", data="G0\n", upload=again["upload"], offset=4
            )
        assert gone.value.code == 1004
        assert (jobs / "part.gcode").read_bytes() == b"G0 X1\nG0 X2\n"  # the finished one
        process.proc.send_signal(signal.SIGTERM)
        await rpc.close()
        async with asyncio.timeout(EXIT_WAIT):
            assert await process.proc.wait() == 0


async def test_bad_config_stops_start_up_with_one_clear_message(tmp_path: Path) -> None:
    config = tmp_path / "bad.toml"
    config.write_text('[[machines]]\nid = "m"\ndata_port = "/dev/x"\nwindow = 0\n')
    proc = await asyncio.create_subprocess_exec(
        *SERVE, "--config", str(config), stderr=asyncio.subprocess.PIPE
    )
    _, stderr = await proc.communicate()
    assert proc.returncode == 2
    message = stderr.decode()
    assert str(config) in message and "machines[0].window" in message
    assert message.count("\n") == 1


async def test_an_unknown_socket_group_stops_start_up_with_a_clear_message(
    tmp_path: Path,
) -> None:
    config = tmp_path / "group.toml"
    config.write_text(
        f'[daemon]\nsocket = "{tmp_path}/s.sock"\nstate_dir = "{tmp_path}/state"\n'
        'group = "no-such-group-hostd"\n'
    )
    proc = await asyncio.create_subprocess_exec(
        *SERVE, "--config", str(config), stderr=asyncio.subprocess.PIPE
    )
    _, stderr = await proc.communicate()
    assert proc.returncode == 2
    assert "[daemon] group: no group named 'no-such-group-hostd'" in stderr.decode()
    assert not (tmp_path / "s.sock").exists()


async def serve_failure(config: Path) -> tuple[int, str]:
    """Start a daemon that must not start: its exit status and what it printed on stderr."""
    proc = await asyncio.create_subprocess_exec(
        *SERVE, "--config", str(config), stderr=asyncio.subprocess.PIPE
    )
    async with asyncio.timeout(45):  # against a hang: its imports took past 20 s under load
        _, stderr = await proc.communicate()
    assert proc.returncode is not None
    return proc.returncode, stderr.decode()


def socket_config(tmp_path: Path, socket_path: Path) -> Path:
    config = tmp_path / "socket.toml"
    config.write_text(
        f'[daemon]\nsocket = "{socket_path}"\nstate_dir = "{tmp_path}/state"\n\n'
        '[[machines]]\nid = "sim1"\ndata_port = "sim"\n'
    )
    return config


async def test_a_socket_path_in_use_is_one_line_and_exit_1(tmp_path: Path) -> None:
    path = tmp_path / "hostd.sock"
    live = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    live.bind(str(path))
    live.listen()
    try:
        status, stderr = await serve_failure(socket_config(tmp_path, path))
    finally:
        live.close()
    assert status == 1
    assert stderr == f"hostd: {path} is in use: another process listens on it\n"
    assert not (tmp_path / "state").exists()  # refused before anything was built


async def test_a_planted_symlink_is_one_line_and_exit_1(tmp_path: Path) -> None:
    path = tmp_path / "hostd.sock"
    path.symlink_to("/etc/passwd")
    status, stderr = await serve_failure(socket_config(tmp_path, path))
    assert status == 1
    assert stderr == (
        f"hostd: {path} is a symbolic link; refusing to follow or remove it"
        " (remove it yourself if it is yours)\n"
    )
    assert path.is_symlink()


async def test_a_directory_others_may_write_is_one_line_and_exit_1(tmp_path: Path) -> None:
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    status, stderr = await serve_failure(socket_config(tmp_path, shared / "hostd.sock"))
    assert status == 1
    assert stderr.startswith(f"hostd: the socket's directory {shared} is writable by others")
    assert stderr.count("\n") == 1


async def test_a_failure_at_bind_time_is_still_one_line_not_a_traceback(tmp_path: Path) -> None:
    """Past the early check, at bind() inside the daemon's task group: unwrapped, one line."""
    path = tmp_path / ("x" * 120)  # fine to look at, too long for a socket address
    status, stderr = await serve_failure(socket_config(tmp_path, path))
    assert status == 1
    assert "Traceback" not in stderr
    assert stderr.splitlines()[-1] == (
        f"hostd: cannot create the socket {path}: AF_UNIX path too long"
    )


async def test_max_clients_and_line_timeout_from_the_config_hold_in_the_daemon(
    tmp_path: Path,
) -> None:
    config = tmp_path / "limits.toml"
    config.write_text(
        f'[daemon]\nsocket = "{tmp_path}/hostd.sock"\nstate_dir = "{tmp_path}/state"\n'
        "max_clients = 1\nline_timeout = 0.3\n"
    )
    async with daemon_process(tmp_path, config) as process:
        await process.message(b"READY=1")
        first_reader, first = await asyncio.open_unix_connection(process.socket_path)
        first.write(b'{"jsonrpc": "2.0", "method": "daemon.info", "id": 1}\n')
        async with asyncio.timeout(10):
            assert json.loads(await first_reader.readline())["result"]["machines"] == []
            reader, writer = await asyncio.open_unix_connection(process.socket_path)
            assert json.loads(await reader.readline())["error"]["code"] == -32000
            assert await reader.read() == b""
        writer.close()
        # The one admitted client leaves a line half-sent: closed after line_timeout.
        first.write(b'{"jsonrpc": "2.0"')
        async with asyncio.timeout(10):
            error = json.loads(await first_reader.readline())["error"]
            assert error["message"] == "request line not finished within 0.3 s"
            assert await first_reader.read() == b""
        first.close()
        process.proc.send_signal(signal.SIGTERM)
        async with asyncio.timeout(EXIT_WAIT):
            assert await process.proc.wait() == 0


async def test_the_daemon_on_asyncios_own_loop_runs_a_job_pauses_and_stops_cleanly(
    tmp_path: Path,
) -> None:
    """uvloop is the default (and the suite's loop); asyncio's own is the other choice."""
    config = write_config(tmp_path, 'event_loop = "asyncio"')
    async with daemon_process(tmp_path, config) as process:
        rpc = await ready_client(process)
        await process.message(b"WATCHDOG=1")
        # Moves of about 5 ms on the simulated board (2 mm at F3000, ten times real speed):
        # its 48-block planner holds some 0.25 s, more than a loaded suite keeps a daemon
        # just started off the CPU. (With 1 mm at F6000 the job stopped short of 20
        # answered lines in one CI run; the wait's timeout then hid how it ended.)
        program = "".join(f"G1 X{2 * (i % 2)} F3000\n" for i in range(300))
        await rpc.call("file.upload", name="short.gcode", data=program)
        await rpc.call("subscribe", topics=["job"], machine="sim1")
        job_id = (await rpc.call("job.start", machine="sim1", file="short.gcode"))["job"]
        await follow_until_acked(rpc, job_id, 20)
        assert (await rpc.call("job.pause", machine="sim1"))["state"] == "paused"
        assert (await rpc.call("job.resume", machine="sim1"))["state"] == "running"
        done = await rpc.notification(
            lambda n: n["method"] == "job" and n["params"]["job"]["state"] == "completed"
        )
        assert done["params"]["job"]["lines_acked"] == 300
        process.proc.send_signal(signal.SIGTERM)
        await rpc.close()
        async with asyncio.timeout(EXIT_WAIT):
            assert await process.proc.wait() == 0
            assert process.proc.stderr is not None
            logs = [json.loads(line) for line in (await process.proc.stderr.read()).splitlines()]
        assert [r["loop"] for r in logs if r["event"] == "hostd ready"] == ["asyncio"]


@contextlib.asynccontextmanager
async def board_process(path: Path, *board: str) -> AsyncIterator[None]:
    """A simulated g2core in a process of its own (`python -m hostd.sim`), as a real board
    outlives the daemon: its port at `path`, its moves at twice real speed. `board`:
    more of its options (`--grbl grblhal`: a grblHAL board instead)."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "hostd.sim",
        "--data",
        str(path),
        "--speed-factor",
        "2",
        *board,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.DEVNULL,
    )
    try:
        assert proc.stdout is not None
        async with asyncio.timeout(60):  # its imports, on a loaded machine
            assert (await proc.stdout.readline()).startswith(b"data ")
        yield
    finally:
        if proc.returncode is None:
            proc.terminate()
        await proc.wait()


async def test_after_a_sigkill_mid_job_the_restart_stops_the_board_still_running_it(
    tmp_path: Path,
) -> None:
    """The daemon dies mid-job; the board, which does not, runs on through the lines it
    holds and would then stand with its spindle on, nobody watching. The next daemon stops
    it as it connects (docs/operations.md, "When the daemon stops")."""
    port = tmp_path / "ttyACM0"
    config = write_config(tmp_path)
    config.write_text(config.read_text().replace('data_port = "sim"', f'data_port = "{port}"'))
    # 50 mm moves at F3000: half a second each on this board, for 200 of them.
    program = "G21 G90 M3 S8000\n" + "".join(
        f"G1 X{(i % 2) * 50} Y{i * 0.1:.1f} F3000\n" for i in range(400)
    )
    async with board_process(port):
        async with daemon_process(tmp_path, config) as process:
            rpc = await ready_client(process)
            await rpc.call("file.upload", name="part.gcode", data=program)
            await rpc.call("subscribe", topics=["job"], machine="sim1")
            job_id = (await rpc.call("job.start", machine="sim1", file="part.gcode"))["job"]
            await follow_until_acked(rpc, job_id, 8)
            process.proc.kill()
            await process.proc.wait()
            await rpc.close()

        async with daemon_process(tmp_path, config) as process:
            rpc = await ready_client(process)  # idle: at rest, not 200 s of moves later
            status = await rpc.call("machine.status", machine="sim1")
            assert status["state"]["name"] in ("PROGRAM_STOP", "PROGRAM_END"), status
            assert (await rpc.call("job.get", job=job_id))["state"] == "interrupted"
            async with asyncio.timeout(10):
                while (status.get("spindle") or {}).get("state") != "off":
                    status = (await rpc.notification(lambda n: n["method"] == "status"))["params"][
                        "snapshot"
                    ]
            process.proc.send_signal(signal.SIGTERM)
            await rpc.close()
            async with asyncio.timeout(EXIT_WAIT):
                assert await process.proc.wait() == 0


async def test_after_a_sigkill_a_grblhal_board_busy_with_the_job_is_stopped_while_connecting(
    tmp_path: Path,
) -> None:
    """A grblHAL board left with its 1,024-byte buffer full of the job's moves answers `?`
    but no handshake line until they end. The next daemon does not wait for them, nor
    time out and reopen the port again and again: it stops the board as a cancel does
    (here `startup_motion = true`: the reset at rest), then connects (docs/dialects.md,
    "A board busy at connect")."""
    port = tmp_path / "ttyACM0"
    config = write_config(tmp_path)
    config.write_text(
        config.read_text().replace(
            'data_port = "sim"',
            f'data_port = "{port}"\ndialect = "grbl"\nstartup_motion = true',
        )
    )
    # 2 mm moves at F3000, 20 ms each at twice real speed: 400 of them take 8 s, and the
    # board's buffer and planner hold some 160 (3 s), more than a daemon's restart.
    program = "G21 G90 M3 S800\n" + "".join(
        f"G1 X{(i % 2) * 2} Y{i * 0.5:.1f} F3000\n" for i in range(1, 401)
    )
    async with board_process(port, "--grbl", "grblhal", "--laser"):
        async with daemon_process(tmp_path, config) as process:
            rpc = await ready_client(process)
            await rpc.call("file.upload", name="raster.gcode", data=program)
            await rpc.call("subscribe", topics=["job"], machine="sim1")
            job_id = (await rpc.call("job.start", machine="sim1", file="raster.gcode"))["job"]
            await follow_until_acked(rpc, job_id, 150)  # the board's buffer is full
            process.proc.kill()
            await process.proc.wait()
            await rpc.close()

        async with daemon_process(tmp_path, config) as process:
            rpc = await ready_client(process)  # idle: stopped, not 5 s of moves later
            status = await rpc.call("machine.status", machine="sim1")
            assert status["board_state"] == "Idle" and status["occupied"] is None, status
            assert status["position"]["y"] < 190, status  # not at the job's end (Y200)
            assert (status.get("spindle") or {}).get("state") in (None, "off"), status
            assert (await rpc.call("job.get", job=job_id))["state"] == "interrupted"
            process.proc.send_signal(signal.SIGTERM)
            await rpc.close()
            async with asyncio.timeout(EXIT_WAIT):
                assert await process.proc.wait() == 0
