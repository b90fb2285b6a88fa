"""The configuration file (TOML), validated whole before anything starts.

Keys fixed by running.md: `[daemon] socket, state_dir`; per `[[machines]]`:
`id, dialect, data_port, control_port, baudrate, window, auto_connect`.
`[web]` (docs/web.md) turns on the browser dashboard; without it there is none.
The rest (timings, the jobs quota) is the project's, documented in docs/operations.md.
Invalid config is one `ConfigError` naming the file, the key and the problem.

Each section is declared in the layer that reads it and assembled here, at the
top, so that no layer imports the config from above itself: `[daemon]` is
daemon.py's, a machine's table machine/config.py's (with the keys of the link,
link/config.py, of the session, protocol/dialects.py, and of its dialect, the
dialect's registry entry), `[web]` the dashboard's (api/webconfig.py) and
`[mqtt]` the bridge's (api/mqtt/config.py).
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError, field_validator

from hostd.api.mqtt.config import MqttConfig
from hostd.api.webconfig import WebConfig, split_listen
from hostd.daemon import DaemonConfig
from hostd.machine.config import (
    SIM_PORT,
    MachineConfig,
    MacroConfig,
    MacroParam,
    ProbeConfig,
    ToolSensor,
)

__all__ = [
    "SIM_PORT",
    "Config",
    "ConfigError",
    "DaemonConfig",
    "MachineConfig",
    "MacroConfig",
    "MacroParam",
    "MqttConfig",
    "ProbeConfig",
    "ToolSensor",
    "WebConfig",
    "load_config",
    "parse_config",
    "split_listen",
]


class ConfigError(Exception):
    """Start-up stops here: the message names the file, the key and what is wrong."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Config(_Strict):
    daemon: DaemonConfig = DaemonConfig()
    machines: list[MachineConfig] = []
    web: WebConfig | None = None
    mqtt: MqttConfig | None = None  # absent: no MQTT (docs/mqtt.md)

    @field_validator("machines")
    @classmethod
    def _unique_ids(cls, machines: list[MachineConfig]) -> list[MachineConfig]:
        seen: set[str] = set()
        for m in machines:
            if m.id in seen:
                raise ValueError(f"duplicate machine id {m.id!r}")
            seen.add(m.id)
        return machines

    def machine(self, machine_id: str) -> MachineConfig | None:
        return next((m for m in self.machines if m.id == machine_id), None)


def load_config(path: str | Path) -> Config:
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text") from exc
    return parse_config(data, source=str(path))


def parse_config(data: dict[str, Any], source: str = "<config>") -> Config:
    try:
        return Config.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_describe(exc, data, source)) from exc


def _describe(exc: ValidationError, data: dict[str, Any], source: str) -> str:
    """One line a problem: `file: machines[1].window (id 'mill'): must be >= 1`."""
    lines = []
    for err in exc.errors():
        loc = err["loc"]
        key = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in loc).lstrip(".")
        where = _machine_hint(loc, data)
        problem = "unknown key" if err["type"] == "extra_forbidden" else err["msg"]
        problem = problem.removeprefix("Value error, ")
        lines.append(f"{source}: {key or '(top level)'}{where}: {problem}")
    return "\n".join(lines)


def _machine_hint(loc: tuple[int | str, ...], data: dict[str, Any]) -> str:
    if len(loc) >= 2 and loc[0] == "machines" and isinstance(loc[1], int):
        machines = data.get("machines")
        if isinstance(machines, list) and loc[1] < len(machines):
            entry = machines[loc[1]]
            if isinstance(entry, dict) and isinstance(entry.get("id"), str):
                return f" (machine {entry['id']!r})"
    return ""
