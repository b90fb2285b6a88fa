"""The configuration file (TOML), validated whole before anything starts.

Keys fixed by running.md: `[daemon] socket, state_dir`; per `[[machines]]`:
`id, dialect, data_port, control_port, baudrate, window, auto_connect`.
`[web]` (docs/web.md) turns on the browser dashboard; without it there is none.
The rest (timings, the jobs quota) is the project's, documented in docs/operations.md.
Invalid config is one `ConfigError` naming the file, the key and the problem.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    IPvAnyNetwork,
    ValidationError,
    field_validator,
    model_validator,
)

from hostd.api.mqtt.config import MqttConfig
from hostd.link import BOOTLOADER_BAUD
from hostd.machine.signals import SignalsConfig

SIM_PORT = "sim"


class ConfigError(Exception):
    """Start-up stops here: the message names the file, the key and what is wrong."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class DaemonConfig(_Strict):
    socket: str = "/run/hostd/hostd.sock"
    state_dir: str = "/var/lib/hostd"
    # Members of this group may use the socket (it is created 0660 with this
    # group); root and the daemon's own user always may. None: nobody else.
    group: str | None = None
    log_level: Literal["debug", "info", "warning", "error"] = "info"
    # Clients connected at once; one more is told the daemon is full and closed.
    max_clients: Annotated[int, Field(ge=1, le=10_000)] = 128
    # Seconds a client may leave a request line half-sent before it is disconnected
    # (a client quiet between lines stays connected however long).
    line_timeout: Annotated[float, Field(gt=0, le=3600)] = 10.0
    # Bytes the jobs directory may hold, published files and unfinished
    # uploads together; an upload that would pass it is refused (1009). None: no limit.
    jobs_quota: Annotated[int, Field(gt=0)] | None = None
    # Seconds an unfinished upload may go without a chunk before it is removed.
    upload_expiry: Annotated[float, Field(gt=0)] = 3600.0
    # The event loop the daemon runs on: uvloop, or asyncio's own (docs/performance.md
    # has the figures behind the default; the test suite runs on the default).
    event_loop: Literal["asyncio", "uvloop"] = "uvloop"
    # Reading a whole G-code file (file.analyze, job.recovery, job.start's checks) runs
    # on worker processes (hostd/machine/workers.py), each file within these limits:
    # seconds, and bytes of address space per worker (docs/gcode.md). Past one: 1013.
    analysis_timeout: Annotated[float, Field(gt=0, le=3600)] = 600.0
    analysis_memory: Annotated[int, Field(ge=64 << 20)] = 1 << 30


class SensorConfig(_Strict):
    """Where the fixed tool-length sensor is: machine coordinates, mm."""

    x: Annotated[float, Field(allow_inf_nan=False)]
    y: Annotated[float, Field(allow_inf_nan=False)]


class ProbeConfig(_Strict):
    """running.md's `[machines.probe]`: the touch plate and the tool-length sensor.

    Distances in mm, the feed in mm/min. `tool_sensor` is used by the "probe"
    tool-change policy (docs/operations.md, "Tool changes").
    """

    plate: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)] = 0.0
    feed: Annotated[float, Field(gt=0, le=5000, allow_inf_nan=False)] = 100.0
    max_travel: Annotated[float, Field(gt=0, le=500, allow_inf_nan=False)] = 25.0
    retract: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)] = 2.0
    tool_sensor: SensorConfig | None = None


class MachineConfig(_Strict):
    id: Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")]
    dialect: Literal["g2core", "grbl"] = "g2core"
    data_port: Annotated[str, Field(min_length=1)]
    control_port: str | None = None
    baudrate: Annotated[int, Field(gt=0)] = 115200
    window: Annotated[int, Field(ge=1, le=32)] = 4
    auto_connect: bool = True
    # g2core: seconds of silence before the board is asked for a status report; as
    # long again without an answer and the link is taken for dead. grbl: a `?` no
    # report has answered this long is asked again.
    heartbeat: Annotated[float, Field(gt=0)] = 2.0
    # grbl: seconds without a byte from the board (with 3 `?` unanswered) before the
    # link is taken for dead; longer while the board writes EEPROM or homes.
    link_silence: Annotated[float, Field(gt=0, le=3600)] = 10.0
    # grbl: seconds a homing cycle may keep the board silent; unset, the bound its
    # travel and homing feeds give ($24, $25, $27, $130..).
    homing_timeout: Annotated[float, Field(gt=0, le=3600)] | None = None
    # Seconds to wait for the SYSTEM READY banner and the settings after opening.
    handshake_timeout: Annotated[float, Field(gt=0)] = 5.0
    # Status report interval asked of the board, seconds (g2core's minimum is 0.1).
    status_interval: Annotated[float, Field(ge=0.1)] = 0.25
    # Where lid, laser selection, coolant flow and temperature come from
    # (hostd/machine/signals.py); none configured, none of those faults.
    signals: SignalsConfig = SignalsConfig()
    # Resuming a job (job.start with start_line > 1): the height the tool goes up to
    # before it crosses to the resume point, in machine coordinates (mm); unset, the top
    # of the Z travel the board's settings give. And the seconds the spindle is given to
    # reach its speed before the tool goes down.
    safe_z: Annotated[float, Field(allow_inf_nan=False)] | None = None
    spindle_dwell: Annotated[float, Field(ge=0, le=60)] = 2.0
    # Maintenance commands (grbl `$RST=`, `$N0=`, `$I=`, `$SLP`; docs/operations.md):
    # machine.send always refuses them; machine.maintenance sends them only when true.
    maintenance: bool = False
    # grbl: a startup block ($N0/$N1) that moves runs at every reset. False: after a
    # cancel or a failed job hostd holds the board instead of resetting it (only
    # machine.reset, asked by the operator, resets it). True: it resets as usual.
    startup_motion: bool = False
    # The slowest the tool goes back down to the resume depth, mm/min: the resume plunges
    # at the file's own plunge feed (its last feed move along Z alone) or this, whichever
    # is slower. Unset: the file's.
    plunge_feed: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = None
    # The tool is a laser: a resume moves with the beam off and turns it on, without a
    # dwell, only in position. A grbl board in laser mode ($32=1) counts as one anyway.
    laser: bool = False
    # What a job's M6 does (running.md; docs/operations.md, "Tool changes"): "pause" holds
    # the job for the operator, "probe" holds and then measures the new tool on the
    # `[machines.probe]` tool_sensor, "ignore" strips the M6 with a warning, "refuse"
    # refuses the file at job.start. Unset is "refuse".
    tool_change: Literal["pause", "probe", "ignore", "refuse"] | None = None
    probe: ProbeConfig | None = None

    @model_validator(mode="after")
    def _probe_needs_a_sensor(self) -> MachineConfig:
        if self.tool_change == "probe" and (self.probe is None or self.probe.tool_sensor is None):
            raise ValueError(
                'tool_change = "probe" needs [machines.probe] with tool_sensor = { x = .., y = .. }'
            )
        return self

    @field_validator("baudrate")
    @classmethod
    def _not_the_bootloader_touch(cls, v: int) -> int:
        if v == BOOTLOADER_BAUD:
            raise ValueError(f"{BOOTLOADER_BAUD} baud resets the board into its bootloader")
        return v

    @model_validator(mode="after")
    def _grbl_is_single_port(self) -> MachineConfig:
        if self.dialect == "grbl" and self.control_port is not None:
            raise ValueError("a grbl board has one port: no control_port")
        return self

    @model_validator(mode="after")
    def _sim_is_single_port(self) -> MachineConfig:
        if self.control_port == SIM_PORT and self.data_port != SIM_PORT:
            raise ValueError('control_port = "sim" needs data_port = "sim"')
        return self

    @property
    def simulated(self) -> bool:
        return self.data_port == SIM_PORT


class WebConfig(_Strict):
    """The dashboard's HTTP server (hostd/api/web.py); docs/web.md."""

    # "host:port", "[v6 address]:port"; port 0 picks a free one (tests).
    listen: str
    # False: watch only; the methods that move or change anything are refused.
    control: bool = True
    # Login attempts one address may make a minute (successful ones count too).
    login_attempts: Annotated[int, Field(ge=1, le=1000)] = 5
    # Further names the dashboard answers to (a LAN name, a reverse proxy's): requests
    # naming any other host are refused, against DNS rebinding. IP addresses,
    # `localhost` and the `listen` host always do.
    hosts: list[Annotated[str, Field(min_length=1, max_length=253)]] = []
    # Reverse proxies (addresses or networks) whose X-Forwarded-For and X-Forwarded-Proto
    # are believed: the client address (logs, login limit, connection caps) is then the
    # last one in X-Forwarded-For that is not a trusted proxy. Nobody else's are.
    trusted_proxies: list[IPvAnyNetwork] = []
    # Seconds a new connection has to send its first request's headers; seconds an
    # idle connection (between requests, or an upload's body that stops) stays open.
    header_timeout: Annotated[float, Field(gt=0, le=600)] = 10.0
    idle_timeout: Annotated[float, Field(gt=0, le=3600)] = 60.0
    # Connections (HTTP and WebSocket) at once, in all and from one client address
    # (a trusted proxy counts in the total only). The total is also kept within the
    # descriptors the daemon can spare (docs/web.md).
    max_connections: Annotated[int, Field(ge=1, le=100_000)] = 256
    max_connections_per_address: Annotated[int, Field(ge=1, le=100_000)] = 32
    # Seconds a login session may go unused before it ends.
    session_expiry: Annotated[float, Field(gt=0)] = 7 * 86400.0

    @field_validator("listen")
    @classmethod
    def _host_and_port(cls, listen: str) -> str:
        split_listen(listen)
        return listen

    @property
    def host(self) -> str:
        return split_listen(self.listen)[0]

    @property
    def port(self) -> int:
        return split_listen(self.listen)[1]


def split_listen(listen: str) -> tuple[str, int]:
    """("127.0.0.1", 7080) from "127.0.0.1:7080", ("::1", 7080) from "[::1]:7080"."""
    host, sep, port = listen.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not sep or not host or not port.isdigit() or int(port) > 65535:
        raise ValueError(f"{listen!r}: expected host:port, e.g. 127.0.0.1:7080")
    return host, int(port)


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
