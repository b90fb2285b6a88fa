"""Config files: what loads, and the one clear message for what does not."""

from __future__ import annotations

from pathlib import Path

import pytest

from hostd.config import ConfigError, load_config

GOOD = """
[daemon]
socket = "/run/hostd/hostd.sock"
state_dir = "/var/lib/hostd"

[[machines]]
id = "laser1"
dialect = "g2core"
data_port = "/dev/ttyACM0"
control_port = "/dev/ttyACM1"
baudrate = 115200
window = 4
auto_connect = true

[[machines]]
id = "demo"
data_port = "sim"
"""


GRBL = GOOD + 'dialect = "grbl"\n'  # the second machine, `demo`, on grbl


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "hostd.toml"
    path.write_text(text)
    return path


def test_the_documented_example_loads_with_defaults_filled(tmp_path: Path) -> None:
    config = load_config(write(tmp_path, GOOD))
    laser, demo = config.machines
    assert (laser.id, laser.control_port, laser.window) == ("laser1", "/dev/ttyACM1", 4)
    assert demo.simulated and demo.window == 4 and demo.auto_connect
    assert config.machine("demo") is demo
    assert config.machine("nope") is None
    assert (config.daemon.jobs_quota, config.daemon.upload_expiry) == (None, 3600.0)
    grbl = load_config(write(tmp_path, GOOD + 'dialect = "grbl"\n')).machines[1]
    assert (grbl.dialect, grbl.spec.name) == ("grbl", "grbl")
    assert (grbl.link_silence, grbl.homing_timeout) == (10.0, None)  # grbl's liveness


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (GOOD.replace("window = 4", "window = 0"), "machines[0].window (machine 'laser1'):"),
        (GOOD.replace("window = 4", 'window = "four"'), "machines[0].window"),
        (GOOD.replace("auto_connect = true", "auto_conect = true"), "auto_conect"),
        (GOOD.replace('id = "demo"', 'id = "laser1"'), "duplicate machine id 'laser1'"),
        (GOOD.replace("baudrate = 115200", "baudrate = 1200"), "bootloader"),
        (GOOD.replace("[daemon]", "[deamon]"), "deamon: unknown key"),
        (GOOD.replace('dialect = "g2core"', 'dialect = "marlin"'), "machines[0].dialect"),
        (GOOD.replace('data_port = "sim"', ""), "machines[1].data_port"),
        ("[[machines]\nid=", "not valid TOML"),
        (GOOD.replace("[daemon]", "[daemon]\njobs_quota = 0"), "daemon.jobs_quota"),
        (GOOD.replace("[daemon]", '[daemon]\njobs_quota = "2G"'), "daemon.jobs_quota"),
        (GOOD.replace("[daemon]", "[daemon]\nupload_expiry = 0"), "daemon.upload_expiry"),
        (GRBL + "link_silence = 0", "machines[1].link_silence (machine 'demo')"),
        (GRBL + "homing_timeout = -5", "machines[1].homing_timeout"),
        (GRBL + "homing_timeout = 7200", "machines[1].homing_timeout"),
        # A dialect's own keys are unknown on another dialect's machine.
        (GOOD.replace("window = 4", "link_silence = 5"), "machines[0].link_silence"),
        (GRBL + "window = 4", "machines[1].window (machine 'demo'): unknown key"),
        (
            GRBL.replace('data_port = "sim"', 'data_port = "/dev/ttyUSB0"\ncontrol_port = "/x"'),
            "a grbl board has one port: no control_port",
        ),
        (GOOD.replace('dialect = "g2core"', 'dialect = "marlin"'), "one of g2core, grbl"),
        (GOOD.replace("window = 4", "window = 4\nplunge_feed = 0"), "machines[0].plunge_feed"),
        (GOOD.replace("window = 4", "window = 4\nplunge_feed = nan"), "machines[0].plunge_feed"),
    ],
)
def test_bad_config_names_file_key_and_problem(tmp_path: Path, text: str, expected: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    message = str(err.value)
    assert message.startswith(str(path))
    assert expected in message


def test_unknown_key_is_called_that(tmp_path: Path) -> None:
    path = write(tmp_path, GOOD.replace("auto_connect = true", "auto_conect = true"))
    with pytest.raises(ConfigError, match="unknown key"):
        load_config(path)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "absent.toml")


def test_every_example_in_config_loads() -> None:
    examples = sorted((Path(__file__).resolve().parent.parent / "config").glob("*.toml"))
    assert len(examples) >= 2
    for path in examples:
        config = load_config(path)
        assert config.machines, path


MACRO = (
    GOOD
    + """
[[machines.macros]]
name = "park"
text = "G53 G0 Z{z}\\nG0 X{x}"
params = { z = { min = -10, max = 0, default = 0 }, x = { min = 0, max = 300 } }
"""
)


def test_a_macro_loads_with_its_params(tmp_path: Path) -> None:
    config = load_config(write(tmp_path, MACRO))
    macro = config.machines[1].macros[0]
    assert macro.name == "park" and macro.params["x"].max == 300


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (("X{x}", "X{x} Y{y}"), "no param y"),  # a placeholder with no param
        (("X{x}", "X10"), "param x is not in its text"),
        (("min = 0, max = 300", "min = 300, max = 0"), "above max"),
        (("default = 0", "default = 5"), "outside"),
        (('name = "park"', 'name = "park me"'), "machines[1].macros[0].name"),
        (("x = {", "X = {"), "params"),
        (("max = 300", "max = inf"), "params.x.max"),
    ],
)
def test_bad_macros_are_refused_at_start(
    tmp_path: Path, change: tuple[str, str], expected: str
) -> None:
    path = write(tmp_path, MACRO.replace(*change))
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert expected in str(err.value)


def test_a_macro_name_twice_is_refused(tmp_path: Path) -> None:
    twice = MACRO + MACRO[MACRO.index("[[machines.macros]]") :]
    with pytest.raises(ConfigError) as err:
        load_config(write(tmp_path, twice))
    assert "park is named twice" in str(err.value)
