"""A machine's table in the config file (`[[machines]]`), assembled from each layer's keys.

The protocol's (`SessionConfig`: the dialect and the session's timings), the
link's (`PortConfig`: ports and baud rate) and the machine layer's own (its
signals, a resume's heights and feeds, maintenance, laser) sit flat in one
table, as running.md fixes them. The dialect adds its own keys (its
registry entry's `options`, hostd/protocol/dialects.py): a machine's config
is an instance of `MachineConfig` and of its dialect's options at once, so
a key of another dialect is refused by name like any unknown key.
"""

from __future__ import annotations

import re
from typing import Annotated, Any, Final, Literal, Self, cast

from pydantic import BaseModel, ConfigDict, Field, create_model, field_validator, model_validator
from pydantic_core.core_schema import ValidatorFunctionWrapHandler

from hostd.link.config import PortConfig
from hostd.machine.signals import SignalsConfig
from hostd.protocol.dialects import DEFAULT, DialectOptions, SessionConfig, UnknownDialect, lookup

SIM_PORT: Final = "sim"


# A macro's placeholder: `{name}`, a lower-case name (docs/operations.md, "Macros").
PLACEHOLDER = re.compile(r"\{([a-z_][a-z0-9_]{0,31})\}")
_Bound = Annotated[float, Field(allow_inf_nan=False, ge=-1_000_000, le=1_000_000)]


class MacroParam(BaseModel):
    """One parameter of a macro: a number within [min, max], never text (a value can
    then only ever be digits, a sign and a point: it cannot start a line or a command)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    min: _Bound
    max: _Bound
    default: _Bound | None = None
    integer: bool = False

    @model_validator(mode="after")
    def _ordered(self) -> MacroParam:
        if self.min > self.max:
            raise ValueError(f"min {self.min:g} is above max {self.max:g}")
        if self.default is not None and not self.min <= self.default <= self.max:
            raise ValueError(f"default {self.default:g} is outside {self.min:g}..{self.max:g}")
        return self


class MacroConfig(BaseModel):
    """`[[machines.macros]]`: a named G-code snippet, its lines run as one job."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: Annotated[str, Field(pattern=r"^[A-Za-z0-9_.-]{1,64}$")]
    text: Annotated[str, Field(min_length=1, max_length=8192)]
    params: dict[Annotated[str, Field(pattern=r"^[a-z_][a-z0-9_]{0,31}$")], MacroParam] = {}

    @model_validator(mode="after")
    def _placeholders_named(self) -> MacroConfig:
        used = set(PLACEHOLDER.findall(self.text))
        unknown = sorted(used - set(self.params))
        if unknown:
            raise ValueError(f"macro {self.name!r}: no param {', '.join(unknown)} for its text")
        unused = sorted(set(self.params) - used)
        if unused:
            raise ValueError(f"macro {self.name!r}: param {', '.join(unused)} is not in its text")
        return self


class ToolSensor(BaseModel):
    """Where the fixed tool-length sensor is, in machine coordinates (mm)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    x: Annotated[float, Field(allow_inf_nan=False)]
    y: Annotated[float, Field(allow_inf_nan=False)]


class ProbeConfig(BaseModel):
    """running.md's `[machines.probe]`: the touch plate, and the tool-length sensor.

    The plate, feed, travel and retract are `machine.probe`'s defaults (a client's
    params win); `tool_sensor` is where the `probe` tool-change policy measures a
    new tool. All in mm and mm/min, whatever units the board is in.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    plate: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)] | None = None
    feed: Annotated[float, Field(gt=0, le=5000, allow_inf_nan=False)] = 100.0
    max_travel: Annotated[float, Field(gt=0, le=500, allow_inf_nan=False)] = 25.0
    retract: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)] = 2.0
    tool_sensor: ToolSensor | None = None


class MachineConfig(SessionConfig, PortConfig):
    model_config = ConfigDict(extra="forbid", frozen=True)

    id: Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")]
    auto_connect: bool = True
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
    # The slowest the tool goes back down to the resume depth, mm/min: the resume plunges
    # at the file's own plunge feed (its last feed move along Z alone) or this, whichever
    # is slower. Unset: the file's.
    plunge_feed: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = None
    # The tool is a laser: a resume moves with the beam off and turns it on, without a
    # dwell, only in position. A grbl board in laser mode ($32=1) counts as one anyway.
    laser: bool = False
    # The touch plate and the tool-length sensor (running.md `[machines.probe]`).
    probe: ProbeConfig = ProbeConfig()
    # What a job's M6 does (running.md; docs/operations.md, "Tool changes"): "pause" holds
    # the job for the operator, "probe" holds and then measures the new tool on the
    # `[machines.probe]` tool_sensor, "ignore" strips the M6 with a warning, "refuse"
    # refuses the file at job.start. Unset is "refuse".
    tool_change: Literal["pause", "probe", "ignore", "refuse"] | None = None
    # The most a laser test-fire (machine.laser_test) may ask, percent of full power.
    laser_test_max: Annotated[float, Field(gt=0, le=100)] = 10.0
    # Named G-code snippets with parameters (macro.list, macro.run).
    macros: list[MacroConfig] = Field(default_factory=list)

    @field_validator("macros")
    @classmethod
    def _macro_names_once(cls, macros: list[MacroConfig]) -> list[MacroConfig]:
        names = [m.name for m in macros]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise ValueError(f"macro {', '.join(twice)} is named twice")
        return macros

    def __new__(cls, *args: Any, **data: Any) -> Self:
        """`MachineConfig(dialect=..., ...)` is the dialect's class, as validation gives."""
        if cls is MachineConfig and data:
            return cast(Self, super().__new__(_with_options(data) or cls))
        return super().__new__(cls)

    @model_validator(mode="wrap")
    @classmethod
    def _with_the_dialects_keys(cls, data: Any, handler: ValidatorFunctionWrapHandler) -> Any:
        """Validate a table as its dialect's class: the dialect's keys are known there."""
        if cls is MachineConfig and isinstance(data, dict):
            model = _with_options(data)
            if model is not None:
                return model.model_validate(data)
        return handler(data)  # an unknown dialect: the `dialect` field names the known ones

    @model_validator(mode="after")
    def _ports_the_board_has(self) -> Self:
        spec = lookup(self.dialect)
        if self.control_port is not None and spec.ports < 2:
            raise ValueError(f"a {spec.name} board has one port: no control_port")
        return self

    @model_validator(mode="after")
    def _probe_needs_a_sensor(self) -> Self:
        if self.tool_change == "probe" and self.probe.tool_sensor is None:
            raise ValueError(
                'tool_change = "probe" needs [machines.probe] with tool_sensor = { x = .., y = .. }'
            )
        return self

    @model_validator(mode="after")
    def _sim_is_single_port(self) -> Self:
        if self.control_port == SIM_PORT and self.data_port != SIM_PORT:
            raise ValueError('control_port = "sim" needs data_port = "sim"')
        return self

    @property
    def simulated(self) -> bool:
        return self.data_port == SIM_PORT


_classes: dict[type[DialectOptions], type[MachineConfig]] = {}


def _with_options(data: dict[str, Any]) -> type[MachineConfig] | None:
    """The config class of the dialect `data` names: MachineConfig and its options."""
    name = data.get("dialect", DEFAULT)
    try:
        options = lookup(name).options if isinstance(name, str) else None
    except UnknownDialect:
        return None
    if options is None:
        return None
    model = _classes.get(options)
    if model is None:
        bases: tuple[type[MachineConfig], ...] = (MachineConfig, options)  # type: ignore[assignment]
        model = create_model(
            f"MachineConfig_{options.__module__.replace('.', '_')}_{options.__name__}",
            __base__=bases,
            __module__=__name__,
        )
        _classes[options] = model
        globals()[model.__name__] = model  # found by name, as pickle looks a class up
    return model
