"""The unit as it really runs: systemd as PID 1 in a Debian container (systemd-nspawn),
hostd installed and started as docs/operations.md says, `[web]` and `[mqtt]` on.

Run by `make service-test` (HOSTD_SERVICE_TEST=1), not by `make unit`: the first run
builds the Debian root with debootstrap (a few minutes), cached in /var/cache/hostd-test.
The container shares the host's network, so the test reaches the dashboard on loopback and
the daemon reaches the test's mosquitto. The root is booted `--volatile=overlay`: every
run starts from the same clean system.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import aiohttp
import pytest

from tests.mqtt.conftest import Broker, free_port, watching

pytestmark = pytest.mark.asyncio

ROOT = Path(__file__).resolve().parent.parent.parent
CACHE = Path(os.environ.get("HOSTD_TEST_CACHE", "/var/cache/hostd-test"))
PACKAGES = "systemd,systemd-sysv,python3,dbus,procps,iproute2"
SUITE = "bookworm"  # Raspberry Pi OS (bookworm) is Debian bookworm
MIRROR = os.environ.get("HOSTD_DEBIAN_MIRROR", "http://deb.debian.org/debian")
SITE = (
    Path(sys.prefix)
    / "lib"
    / f"python{sys.version_info.major}.{sys.version_info.minor}"
    / "site-packages"
)
WAIT = 60.0


def debian_root() -> Path:
    """A minimal Debian with systemd and python3, built once and kept."""
    root = CACHE / f"{SUITE}-{PACKAGES.replace(',', '_')}"
    if (root / "usr" / "lib" / "systemd" / "systemd").exists():
        return root
    CACHE.mkdir(parents=True, exist_ok=True)
    building = root.with_name(root.name + ".building")
    shutil.rmtree(building, ignore_errors=True)
    subprocess.run(
        ["debootstrap", "--variant=minbase", f"--include={PACKAGES}", SUITE, str(building), MIRROR],
        check=True,
        stdout=subprocess.DEVNULL,
    )
    building.rename(root)
    return root


class Container:
    """A booted container; `run` is a command inside it, as root (nsenter)."""

    def __init__(self, proc: subprocess.Popen[bytes], log: Path) -> None:
        self.proc = proc
        self.log = log
        self.leader = 0

    def run(self, *argv: str, check: bool = True) -> str:
        done = subprocess.run(
            [
                "nsenter",
                f"--target={self.leader}",
                "--mount",
                "--uts",
                "--ipc",
                "--pid",
                "--",
                *argv,
            ],
            capture_output=True,
            text=True,
            check=False,
        )
        if check and done.returncode != 0:
            raise AssertionError(f"{argv}: {done.returncode}\n{done.stdout}\n{done.stderr}")
        return done.stdout

    def show(self, *props: str) -> dict[str, str]:
        out = self.run("systemctl", "show", "hostd", *(f"-p{p}" for p in props))
        return dict(line.split("=", 1) for line in out.splitlines() if "=" in line)

    def wait(self, what: str, check: Callable[[], bool], timeout: float = WAIT) -> None:
        deadline = time.monotonic() + timeout
        while not check():
            if time.monotonic() > deadline:
                raise AssertionError(
                    f"{what} within {timeout} s; container log:\n" + self.log.read_text()[-4000:]
                )
            time.sleep(0.2)


def _leader(nspawn_pid: int) -> int:
    """The container's PID 1 (systemd), as the host sees it: the child of systemd-nspawn."""
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            with contextlib.suppress(OSError):
                stat = Path(f"/proc/{entry}/stat").read_text()
                if int(stat.rsplit(")", 1)[1].split()[1]) == nspawn_pid:
                    return int(entry)
    return 0


@contextlib.contextmanager
def booted(tmp_path: Path) -> Iterator[Container]:
    root = debian_root()
    hostd = tmp_path / "hostd"  # /usr/bin/hostd inside: this checkout on Debian's python3
    hostd.write_text(
        "#!/usr/bin/python3\n"
        "import sys\n"
        'sys.path[:0] = ["/opt/hostd/src", "/opt/hostd/site"]\n'
        "from hostd.cli.main import main\n"
        "sys.exit(main())\n"
    )
    hostd.chmod(0o755)
    log = tmp_path / "container.log"
    name = f"hostd-test-{os.getpid()}"
    proc = subprocess.Popen(
        [
            "systemd-nspawn",
            f"--directory={root}",
            f"--machine={name}",
            "--volatile=overlay",
            "--boot",
            "--register=no",
            "--keep-unit",
            f"--bind-ro={ROOT}:/opt/hostd/src",
            f"--bind-ro={SITE}:/opt/hostd/site",
            f"--bind-ro={hostd}:/usr/bin/hostd",
            f"--bind-ro={tmp_path / 'etc'}:/opt/hostd/etc",
        ],
        stdin=subprocess.DEVNULL,
        stdout=log.open("wb"),
        stderr=subprocess.STDOUT,
        env={**os.environ, "SYSTEMD_NSPAWN_TMPFS_TMP": "0"},
    )
    container = Container(proc, log)
    try:
        container.wait(
            "systemd-nspawn starts systemd",
            lambda: bool(_leader(proc.pid)) or proc.poll() is not None,
        )
        assert proc.poll() is None, "systemd-nspawn exited:\n" + log.read_text()[-4000:]
        container.leader = _leader(proc.pid)

        def up() -> bool:
            state = container.run("systemctl", "is-system-running", check=False).strip()
            return state in ("running", "degraded")

        container.wait("the container's systemd finishes booting", up)
        yield container
    finally:
        proc.terminate()
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(20)
        if proc.poll() is None:
            proc.kill()
            proc.wait()


async def test_the_unit_runs_hostd_with_web_and_mqtt_under_systemd(
    tmp_path: Path, broker: Broker
) -> None:
    port = free_port()
    etc = tmp_path / "etc"
    etc.mkdir()
    (etc / "hostd.toml").write_text(
        "[daemon]\n"
        'group = "hostd"\n'
        "\n[[machines]]\n"
        'id = "sim1"\n'
        'data_port = "sim"\n'
        f'\n[web]\nlisten = "127.0.0.1:{port}"\n'
        f'\n[mqtt]\nurl = "{broker.url}"\ntopic_prefix = "svc/pi"\n'
    )
    with booted(tmp_path) as box:
        # docs/operations.md, "Installing as a service", step by step.
        box.run(
            "useradd",
            "--system",
            "--user-group",
            "--groups",
            "dialout",
            "--home-dir",
            "/var/lib/hostd",
            "hostd",
        )
        box.run(
            "install", "-m", "0644", "/opt/hostd/src/systemd/hostd.service", "/etc/systemd/system/"
        )
        box.run("install", "-d", "-m", "0750", "-o", "root", "-g", "hostd", "/etc/hostd")
        box.run(
            "install",
            "-m",
            "0640",
            "-g",
            "hostd",
            "/opt/hostd/etc/hostd.toml",
            "/etc/hostd/hostd.toml",
        )
        async with watching(broker, "svc/pi/online") as watcher:
            box.run("systemctl", "daemon-reload")
            try:
                box.run("systemctl", "enable", "--now", "hostd")  # returns once READY=1 came
            except AssertionError as exc:
                journal = box.run("journalctl", "-u", "hostd", "--no-pager", check=False)
                raise AssertionError(f"{exc}\n{journal[-4000:]}") from None
            # READY=1: Type=notify is active only after it; the STATUS= line names the machine.
            state = box.show("ActiveState", "SubState", "StatusText", "MainPID", "NRestarts")
            assert (state["ActiveState"], state["SubState"]) == ("active", "running"), state
            assert "sim1" in state["StatusText"], state
            # MQTT: the daemon, inside the sandbox, reached the broker on the host.
            assert await watcher.state("svc/pi/online", lambda p: p == "online") == "online"
        # The socket: the group's, 0660, owned by the service's user.
        mode = box.run("stat", "-c", "%a %U %G", "/run/hostd/hostd.sock").split()
        assert mode == ["660", "hostd", "hostd"], mode
        # The web port, and a token made with sudo as the docs say, read by the service.
        token = box.run("hostd", "token", "create", "--config", "/etc/hostd/hostd.toml").strip()
        owner = box.run("stat", "-c", "%a %U %G", "/var/lib/hostd/web-tokens.json").split()
        assert owner == ["640", "hostd", "hostd"], owner
        # The sandbox as systemd parsed it: the Pi's UARTs allowed, the network families.
        sandbox = box.show("RestrictAddressFamilies")
        allowed = box.run("systemctl", "show", "hostd", "-pDeviceAllow").splitlines()
        for device in ("char-ttyACM", "char-ttyUSB", "char-ttyAMA", "char-ttyS"):
            assert f"DeviceAllow={device} rw" in allowed, allowed
        assert set(sandbox["RestrictAddressFamilies"].split()) == {"AF_UNIX", "AF_INET", "AF_INET6"}
        limits = box.run("cat", f"/proc/{state['MainPID']}/limits")
        soft, hard = next(
            line.split()[3:5] for line in limits.splitlines() if line.startswith("Max open files")
        )
        # LimitNOFILE=65536 where the host allows it (this test machine's hard limit may be
        # lower, and the container cannot raise it): soft and hard alike, never 1024.
        assert soft == hard and int(soft) > 1024, limits
        async with aiohttp.ClientSession() as http:
            url = f"http://127.0.0.1:{port}"
            async with http.get(f"{url}/login") as r:
                assert r.status == 200
            async with http.get(
                f"{url}/session", headers={"Authorization": f"Bearer {token}"}
            ) as r:
                assert r.status == 200, await r.text()
        # The watchdog: a daemon that stops answering is killed and started again.
        pid = state["MainPID"]
        box.run("kill", "-STOP", pid)
        box.wait(
            "the watchdog restarts the stopped daemon",
            lambda: (
                box.show("MainPID", "ActiveState")["MainPID"] not in ("0", pid)
                and box.show("ActiveState")["ActiveState"] == "active"
            ),
            timeout=120,
        )
        assert int(box.show("NRestarts")["NRestarts"]) == 1
        journal = box.run("journalctl", "-u", "hostd", "--no-pager", check=False)
        assert "Watchdog timeout" in journal, journal[-3000:]
