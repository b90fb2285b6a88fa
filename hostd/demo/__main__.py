"""`make demo`: the daemon, a simulated machine, a sample job run from the CLI.

Every step is a real command a user could type: `hostd serve` with a demo
config (one simulated g2core on a pseudo-terminal pair), `hostd run` with
its live progress bar, `hostd hold` and `hostd resume` a third of the way
in, `hostd jobs` for the job's history row, then SIGTERM to the daemon.
Exit status 0 only if every step did what it should.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import socket
import sys
import tempfile
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
    proc = await asyncio.create_subprocess_exec(*HOSTD, *args, env=env)
    if await proc.wait() != 0:
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


async def run(console: Console) -> int:
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
        )
        try:
            await wait_ready(notify, daemon)
            url = f"http://127.0.0.1:{port}/login#token={token}"
            console.print(f"the dashboard, while the demo runs: [bold]{url}[/bold]", soft_wrap=True)
            console.print("hostd is ready; the simulated machine:")
            await hostd("status", env=env)
            console.print(f"\nrunning: hostd run {SAMPLE.name} --machine sim1")
            pauser = asyncio.create_task(hold_and_resume(sock, env, console))
            await hostd("run", str(SAMPLE), "--machine", "sim1", env=env)
            await pauser
            console.print("\nthe job's history row: hostd jobs --machine sim1 --limit 1")
            await hostd("jobs", "--machine", "sim1", "--limit", "1", env=env)
            if sys.stdin.isatty():
                console.print(f"\nthe dashboard stays up at {url}: Ctrl-C stops the demo")
                with contextlib.suppress(KeyboardInterrupt, asyncio.CancelledError):
                    await daemon.wait()
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


def main() -> int:
    console = Console()
    try:
        return asyncio.run(run(console))
    except (DemoError, TimeoutError, OSError) as exc:
        console.print(f"[red]demo failed[/red]: {exc or 'timed out'}")
        return 1


if __name__ == "__main__":
    sys.exit(main())
