"""The systemd unit passes systemd-analyze verify; the udev rule names the g2core boards."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_the_unit_verifies_cleanly(tmp_path: Path) -> None:
    analyze = shutil.which("systemd-analyze")
    assert analyze, "systemd-analyze is missing: .ci/run installs Debian's systemd package"
    hostd = Path(sys.executable).parent / "hostd"  # the installed console script
    assert hostd.exists()
    unit = (ROOT / "systemd" / "hostd.service").read_text()
    assert "ExecStart=/usr/bin/hostd serve" in unit
    (tmp_path / "hostd.service").write_text(unit.replace("/usr/bin/hostd", str(hostd)))
    result = subprocess.run(
        [analyze, "verify", "--man=no", str(tmp_path / "hostd.service")],
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    assert result.stderr.strip() == "", result.stderr


def test_the_unit_has_what_running_md_asks_for() -> None:
    unit = (ROOT / "systemd" / "hostd.service").read_text()
    for line in (
        "Type=notify",
        "WatchdogSec=",
        "Restart=on-failure",
        "SupplementaryGroups=dialout",
        "RuntimeDirectory=hostd",
        "StateDirectory=hostd",
        "ConfigurationDirectory=hostd",
        "NoNewPrivileges=yes",
        "ProtectSystem=strict",
        "ProtectHome=yes",
        "PrivateTmp=yes",
        "DevicePolicy=closed",
        "DeviceAllow=char-ttyACM rw",
        "DeviceAllow=char-ttyUSB rw",
        "DeviceAllow=char-ttyAMA rw",  # a Raspberry Pi's GPIO UART, /dev/serial0
        "DeviceAllow=char-ttyS rw",
        "RestrictAddressFamilies=AF_UNIX AF_INET AF_INET6",  # [web] and [mqtt]
        "LimitNOFILE=",
        "SystemCallErrorNumber=EPERM",
    ):
        assert line in unit, line


def test_the_udev_rule_matches_g2core_boards_by_serial() -> None:
    rules = [
        line
        for line in (ROOT / "systemd" / "99-hostd.rules").read_text().splitlines()
        if line and not line.startswith("#")
    ]
    symlinks = [r for r in rules if "SYMLINK+=" in r]
    assert len(symlinks) == 2
    for rule in symlinks:
        assert 'ATTRS{idVendor}=="1d50"' in rule and 'ATTRS{idProduct}=="606d"' in rule
        assert "$attr{serial}" in rule and 'GROUP="dialout"' in rule
