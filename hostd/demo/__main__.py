"""`make demo`: the daemon, a simulated machine, a sample job run from the CLI.

Every step is a real command a user could type: `hostd serve` with a demo
config (one simulated g2core on a pseudo-terminal pair), `hostd run` with
its live progress bar, `hostd hold` and `hostd resume` a third of the way
in, `hostd jobs` for the job's history row. Then the daemon and its dashboard
stay up, with what to try next printed, until Ctrl-C (or SIGTERM); `--once`
stops the daemon as soon as the job is done (the test of the demo uses it).
Exit status 0 only if every step did what it should and the daemon stopped
cleanly.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import socket
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from rich.console import Console

from hostd.api.tokens import TokenStore
from hostd.cli.client import Client

SAMPLE = Path(__file__).with_name("sample.gcode")
HOSTD = [sys.executable, "-m", "hostd"]
CONFIG = """\
[daemon]
socket = "{socket}"
state_dir = "{state}"
log_level = "warning"

[web]
listen = "127.0.0.1:{port}"

[[machines]]
id = "sim1"
data_port = "sim"
auto_connect = true
"""


class DemoError(Exception):
    pass


async def hostd(*args: str, env: dict[str, str]) -> None:
    """One CLI command, its output straight to the terminal; DemoError if it fails."""
    # Its own session: Ctrl-C is the demo's to handle, not each child's.
    proc = await asyncio.create_subprocess_exec(*HOSTD, *args, env=env, start_new_session=True)
    try:
        await proc.wait()
    except asyncio.CancelledError:  # Ctrl-C mid-step: the step goes with the demo
        proc.terminate()
        await proc.wait()
        raise
    if proc.returncode != 0:
        raise DemoError(f"hostd {' '.join(args)} exited {proc.returncode}")


async def wait_ready(notify: socket.socket, daemon: asyncio.subprocess.Process) -> None:
    """Until the daemon says READY=1 over the notify socket, as it would to systemd."""
    loop = asyncio.get_running_loop()
    async with asyncio.timeout(30):
        while b"READY=1" not in await loop.sock_recv(notify, 4096):
            if daemon.returncode is not None:
                raise DemoError("hostd serve exited during start-up")


async def hold_and_resume(sock: str, env: dict[str, str], console: Console) -> None:
    """A third of the way through the job, pause it for a moment and resume it."""
    async with Client(sock) as client:
        await client.call("subscribe", topics=["job"], machine="sim1")
        async with asyncio.timeout(60):
            async for note in client.notifications():
                job = note.params["job"]
                total = job.get("lines_total") or 0
                if job["state"] == "running" and job["lines_acked"] * 3 >= total > 0:
                    break
        console.print("\n[bold]feedhold[/bold]: hostd hold sim1")
        await hostd("hold", "sim1", env=env)
        await asyncio.sleep(1.5)  # let the pause be seen
        console.print("[bold]resume[/bold]: hostd resume sim1")
        await hostd("resume", "sim1", env=env)


async def until_stopped() -> None:
    """Until Ctrl-C or SIGTERM reaches the demo."""
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        await stop.wait()
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)


def next_steps(console: Console, sock: str, url: str) -> None:
    """What a newcomer can try against the running demo, from another terminal."""
    console.rule("the demo keeps running: try it")
    console.print(f"dashboard:  [bold]{url}[/bold]", soft_wrap=True)
    here = Path.cwd()
    sample = SAMPLE.relative_to(here) if SAMPLE.is_relative_to(here) else SAMPLE
    console.print("in another terminal, from this folder:")
    for line in (
        f"export HOSTD_SOCKET={sock}",
        ".venv/bin/hostd status",
        ".venv/bin/hostd send sim1 '{xvm:n}' 'G0 X10 Y10'",
        f".venv/bin/hostd analyze {sample} -m sim1",
        f".venv/bin/hostd run {sample} -m sim1",
        ".venv/bin/hostd watch",
    ):
        console.print(f"  {line}", soft_wrap=True, highlight=False, markup=False)
    console.print("Ctrl-C stops the demo (the daemon, its simulated board and the dashboard).")


async def run(console: Console, *, once: bool = False) -> int:
    with tempfile.TemporaryDirectory(prefix="hostd-demo-") as tmp:
        sock = os.path.join(tmp, "hostd.sock")
        config = Path(tmp) / "demo.toml"
        state = os.path.join(tmp, "state")
        port = _free_port()
        config.write_text(CONFIG.format(socket=sock, state=state, port=port))
        # The dashboard's token, made as `hostd token create` makes it: printed once, kept hashed.
        token = TokenStore(Path(state)).create("demo")
        env = {**os.environ, "HOSTD_SOCKET": sock}
        notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        notify.bind(os.path.join(tmp, "notify"))
        notify.setblocking(False)

        console.rule("hostd demo")
        console.print(f"starting: hostd serve --config {config}")
        daemon = await asyncio.create_subprocess_exec(
            *HOSTD,
            "serve",
            "--config",
            str(config),
            env={**env, "NOTIFY_SOCKET": os.path.join(tmp, "notify")},
            start_new_session=True,
        )
        try:
            await wait_ready(notify, daemon)
            url = f"http://127.0.0.1:{port}/login#token={token}"
            console.print(f"the dashboard, while the demo runs: [bold]{url}[/bold]", soft_wrap=True)
            console.print("hostd is ready; the simulated machine:")
            await hostd("status", env=env)
            console.print(f"\nrunning: hostd run {SAMPLE.name} --machine sim1")
            pauser = asyncio.create_task(hold_and_resume(sock, env, console))
            try:
                await hostd("run", str(SAMPLE), "--machine", "sim1", env=env)
            except BaseException:
                pauser.cancel()  # owned here: ended before the error goes on
                await asyncio.wait({pauser})
                raise
            await pauser
            console.print("\nthe job's history row: hostd jobs --machine sim1 --limit 1")
            await hostd("jobs", "--machine", "sim1", "--limit", "1", env=env)
            if not once:
                next_steps(console, sock, url)
                stopped = asyncio.create_task(until_stopped())
                died = asyncio.create_task(daemon.wait())
                await asyncio.wait({stopped, died}, return_when=asyncio.FIRST_COMPLETED)
                for task in (stopped, died):
                    task.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await task
                if daemon.returncode is not None:
                    raise DemoError(f"hostd serve exited {daemon.returncode} while the demo ran")
        finally:
            if daemon.returncode is None:
                daemon.send_signal(signal.SIGTERM)
            code = await daemon.wait()
            notify.close()
        if code != 0:
            raise DemoError(f"hostd serve exited {code} on SIGTERM")
        console.print("\nhostd stopped cleanly (SIGTERM).")
        console.rule("demo complete")
    return 0


def _free_port() -> int:
    """A loopback port nothing listens on now (the daemon binds it a moment later)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def main(argv: Sequence[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else list(argv)
    console = Console()
    try:
        return asyncio.run(run(console, once="--once" in args))
    except (DemoError, TimeoutError, OSError) as exc:
        console.print(f"[red]demo failed[/red]: {exc or 'timed out'}")
        return 1


if __name__ == "__main__":
    sys.exit(main())
