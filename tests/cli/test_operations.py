"""`hostd home`, `zero`, `override`, `spindle`, `frame`, `laser-test` and `macro`, as run.

Subprocesses against one `hostd serve` with a simulated g2core (`sim1`) and a
simulated grbl laser (`laser`), over the real socket.
"""

from __future__ import annotations

import asyncio
import json
import re
from collections.abc import Callable
from typing import Any

import pytest

from hostd.cli.client import Client
from tests.cli.conftest import MACHINE, Daemon

LASER = "laser"
EXTRA_CONFIG = (
    f"""
[[machines]]
id = "{LASER}"
dialect = "grbl"
data_port = "sim"
auto_connect = true
laser = true
"""
    + """
[[machines.macros]]
name = "corner"
text = "G21 G90\\nG0 X{x} Y{y}"
params = { x = { min = 0, max = 40 }, y = { min = 0, max = 40, default = 2 } }
"""
)


def laser_idle(daemon: Daemon) -> dict[str, Any]:
    return laser_until(daemon, lambda snap: snap["supervisor"] == "idle")


def laser_until(
    daemon: Daemon, predicate: Callable[[dict[str, Any]], bool], timeout: float = 10.0
) -> dict[str, Any]:
    """The grbl machine's snapshot once `predicate` holds (re-checked on notifications)."""

    async def go() -> dict[str, Any]:
        async with Client(daemon.socket) as c:
            await c.call("subscribe", topics=["status", "supervisor"], machine=LASER)
            notes = c.notifications()
            async with asyncio.timeout(timeout):
                while True:
                    snap: dict[str, Any] = await c.call("machine.status", machine=LASER)
                    if predicate(snap):
                        return snap
                    await notes.__anext__()

    return asyncio.run(go())


def test_home_homes_and_says_so(idle: Daemon) -> None:
    result = idle.cli("home", MACHINE)
    assert result.returncode == 0, result.stderr
    assert f"{MACHINE}: homed" in result.stdout
    assert idle.call("machine.status", machine=MACHINE)["homed"] is True


def test_home_of_some_axes_and_bad_axes(idle: Daemon) -> None:
    assert idle.cli("--json", "home", MACHINE, "z").stdout.strip() == "{}"
    bad = idle.cli("home", MACHINE, "xq")
    assert bad.returncode == 2 and "xyz" in bad.stderr
    twice = idle.cli("home", MACHINE, "xx")
    assert twice.returncode == 2 and "once" in twice.stderr


def test_zero_sets_the_work_position_to_zero(idle: Daemon) -> None:
    idle.call("machine.jog", machine=MACHINE, axes={"x": 3, "y": 2}, feed=3000)
    idle.wait_idle()
    result = idle.cli("--json", "zero", MACHINE, "xy")
    assert result.returncode == 0, result.stderr
    snap = json.loads(result.stdout)
    assert snap["id"] == MACHINE
    text = idle.cli("zero", MACHINE, "XY")
    assert text.returncode == 0, text.stderr
    assert "XY zeroed in G54" in text.stdout
    snap = idle.wait_machine(
        lambda s: abs(s["work_position"]["x"]) < 1e-3 and abs(s["work_position"]["y"]) < 1e-3
    )
    assert snap["machine_position"]["x"] != pytest.approx(0, abs=1e-3)
    missing = idle.cli("zero", MACHINE)
    assert missing.returncode == 2


def test_spindle_on_and_off(idle: Daemon) -> None:
    on = idle.cli("spindle", MACHINE, "on", "--speed", "800", "--ccw")
    assert on.returncode == 0, on.stderr
    assert "spindle ccw at 800" in on.stdout
    off = idle.cli("spindle", MACHINE, "off")
    assert off.returncode == 0 and "spindle off" in off.stdout
    wrong = idle.cli("spindle", MACHINE, "off", "--speed", "5")
    assert wrong.returncode == 2
    negative = idle.cli("spindle", MACHINE, "on", "--speed", "-5")
    assert negative.returncode == 2


def test_override_on_grbl_prints_the_overrides_in_force(daemon: Daemon) -> None:
    laser_idle(daemon)
    result = daemon.cli("override", LASER, "--feed", "120", "--rapid", "25")
    assert result.returncode == 0, result.stderr
    assert "feed 120%, spindle 100%, rapid 25%" in result.stdout
    as_json = daemon.cli("--json", "override", LASER, "--spindle", "70")
    assert json.loads(as_json.stdout) == {"feed": 120, "spindle": 70, "rapid": 25}


def test_override_needs_a_value_and_g2core_takes_its_own_bounds(idle: Daemon) -> None:
    none = idle.cli("override", MACHINE)
    assert none.returncode == 2 and "--feed" in none.stderr
    done = idle.cli("override", MACHINE, "--feed", "110")
    assert done.returncode == 0, done.stderr
    assert "feed 110%, spindle 100%, rapid 100%" in done.stdout
    refused = idle.cli("override", MACHINE, "--rapid", "150")
    assert refused.returncode == 1 and "-32602" in refused.stderr and "5 to 100" in refused.stderr


def test_spindle_on_grbl_shows_in_its_snapshot(daemon: Daemon) -> None:
    laser_idle(daemon)
    result = daemon.cli("spindle", LASER, "on", "--speed", "300")
    assert result.returncode == 0, result.stderr
    laser_until(daemon, lambda snap: (snap["spindle"] or {}).get("state") == "cw")
    # S300 as the board runs it: an earlier test may have left a spindle override on.
    assert re.search(r"^spindle +cw, S\d+$", daemon.cli("status", LASER).stdout, re.M)
    assert daemon.cli("spindle", LASER, "off").returncode == 0
    laser_until(daemon, lambda snap: (snap["spindle"] or {}).get("state") == "off")


def test_frame_traces_a_files_box_and_prints_the_job(
    daemon: Daemon, tmp_path_factory: pytest.TempPathFactory
) -> None:
    laser_idle(daemon)
    path = tmp_path_factory.mktemp("frame") / "box.gcode"
    path.write_text("G21 G90\nG0 X5 Y6\nG1 X15 Y6 F900 S500 M4\nG1 X15 Y16\nM5\n")
    result = daemon.cli("frame", LASER, str(path), "--feed", "3000")
    assert result.returncode == 0, result.stderr
    assert "completed" in result.stdout
    snap = laser_idle(daemon)
    assert (snap["work_position"]["x"], snap["work_position"]["y"]) == (5, 6)  # back at the start


def test_laser_test_fires_and_says_the_beam_is_off(daemon: Daemon) -> None:
    laser_idle(daemon)
    result = daemon.cli("laser-test", LASER, "3", "--seconds", "0.2")
    assert result.returncode == 0, result.stderr
    assert "beam off" in result.stdout
    too_much = daemon.cli("laser-test", LASER, "50")
    assert too_much.returncode == 1 and "laser_test_max" in too_much.stderr


def test_macro_list_and_run(daemon: Daemon) -> None:
    laser_idle(daemon)
    listed = daemon.cli("macro", "list", LASER)
    assert listed.returncode == 0, listed.stderr
    assert "corner" in listed.stdout and "x (0..40), y=2 (0..40)" in listed.stdout
    ran = daemon.cli("macro", "run", LASER, "corner", "x=7.5")
    assert ran.returncode == 0, ran.stderr
    snap = laser_until(daemon, lambda s: s["supervisor"] == "idle" and s["position"]["x"] == 7.5)
    assert snap["position"]["y"] == 2
    bad = daemon.cli("macro", "run", LASER, "corner", "x=5 M3")
    assert bad.returncode == 2 and "NAME=NUMBER" in bad.stderr
    unknown = daemon.cli("macro", "run", LASER, "nope")
    assert unknown.returncode == 1 and "1004" in unknown.stderr
