"""The dialect registry: every controller dialect hostd speaks, each one object.

A dialect is a folder (or a module) of its own that registers one
`DialectSpec`: its session, its words, its G-code capabilities, its realtime
bytes, its simulator and its config schema additions. Everything above
`hostd/protocol` asks the registry (`lookup(name)`) or the machine's session
and never names a dialect; the two built-in dialects (`g2dialect.py`,
`grbl/dialect.py`) register through `register` exactly as a third-party one
does (tests/toydialect/ is one, registered from a test). How to add one, and
the shared vocabulary every dialect maps onto, are in docs/architecture.md,
"Dialects".

The built-ins are imported on the first look-up, not when this module is
imported, so that their modules may import this one.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Annotated, Protocol, Self

from pydantic import BaseModel, ConfigDict, Field, field_validator

from hostd.protocol.commands import Realtime
from hostd.protocol.gcodestate.dialects import Dialect as GcodeDialect
from hostd.protocol.maintenance import Maintenance
from hostd.protocol.states import MachineState

if TYPE_CHECKING:
    from hostd.protocol.session import SessionBase

DEFAULT = "g2core"  # a machine without `dialect`, and a file analysed for no machine
# The modules of the dialects hostd ships; each registers itself when imported.
BUILTIN = ("hostd.protocol.g2dialect", "hostd.protocol.grbl.dialect")

Travel = Mapping[str, tuple[float, float]]


class Keys(Protocol):
    """Something that lists status report keys (the machine layer's signal sources)."""

    def keys(self) -> list[str]: ...


class SessionSettings(Protocol):
    """What a session factory reads of a machine's config.

    The machine layer's `MachineConfig` is one: the fields every dialect
    shares, and the dialect's own options (its `options` model, which the
    config's class inherits, so `DialectOptions.of` finds them).
    """

    @property
    def id(self) -> str: ...
    @property
    def control_port(self) -> str | None: ...
    @property
    def status_interval(self) -> float: ...
    @property
    def heartbeat(self) -> float: ...
    @property
    def handshake_timeout(self) -> float: ...
    @property
    def signals(self) -> Keys: ...


class DialectOptions(BaseModel):
    """A dialect's config schema additions: keys of `[[machines]]` only it reads.

    A subclass declares them as pydantic fields with defaults; the machine's
    config class inherits it, so the keys sit flat in the machine's table (as
    `window` does) and an unknown key is still refused by name.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    @classmethod
    def of(cls, settings: object) -> Self:
        """The options in `settings` (a machine config of this dialect), or the defaults."""
        return settings if isinstance(settings, cls) else cls()


class NoOptions(DialectOptions):
    """A dialect with no keys of its own."""


@dataclass(frozen=True, slots=True)
class Words:
    """What a dialect's board says, in its own words, and what hostd calls it.

    `statuses`: every non-zero answer the board can give to a line, with its own
    text (error 1005's `msg`; the session's `status_text` reads this table).
    `alarms`: its alarm codes and texts (empty where its alarms carry no code).
    `states`: the board's state names or codes and the shared state each is.
    """

    statuses: Mapping[int, str]
    alarms: Mapping[int, str] = field(default_factory=dict)
    states: Mapping[int, MachineState] | Mapping[str, MachineState] = field(default_factory=dict)


def _no_maintenance(text: str, travel: Travel, inches: bool) -> Maintenance | None:
    return None


def _powers_nothing(text: str) -> str | None:
    return None


@dataclass(frozen=True, slots=True)
class DialectSpec:
    """One dialect, as it registers itself.

    - `name`: what `dialect = "..."` says in a machine's config.
    - `session`: the factory of a machine's session, from its config.
    - `words`: its status texts, alarm texts and state mapping.
    - `gcode`: the G-code it reads differently, and the codes it refuses: the
      table the analysis, the job check and a resume's plan use.
    - `encode_line`: a job line as written to the board, refused (InvalidCommand)
      past `max_bytes` (its LF included) or where the board must never read it.
    - `maintenance`: the maintenance command a line is on this board, or None
      (maintenance.py; `travel` in mm, `inches` the board's modal units).
    - `powered`: what a line a client sends would do that a fault blocking a
      job forbids (moves the machine, starts its spindle or beam), or None
      (maintenance.py); `machine.send` and `machine.maintenance` refuse it.
    - `realtime`: the single bytes it reads out of the stream, by hostd's name.
    - `simulator`: "module:factory" of a simulated board (hostd/sim), imported
      only when a machine says `data_port = "sim"`, so that protocol never
      imports sim. The factory takes (data path, control path or None, speed
      factor, history) and gives an object with async `start()` and `close()`.
    - `options`: its config schema additions (`DialectOptions`).
    - `ports`: how many serial ports its board may use (2: a control_port too).

    The object is pickled whole to the analysis workers, so every field is a
    module-level class or function, or plain data.
    """

    name: str
    session: Callable[[SessionSettings], SessionBase]
    words: Words
    gcode: GcodeDialect
    encode_line: Callable[[str, int], bytes]
    simulator: str
    maintenance: Callable[[str, Travel, bool], Maintenance | None] = _no_maintenance
    powered: Callable[[str], str | None] = _powers_nothing
    realtime: Mapping[Realtime, bytes] = field(default_factory=dict)
    options: type[DialectOptions] = NoOptions
    ports: int = 1


class SessionConfig(BaseModel):
    """The keys of a machine's table every dialect's session reads (the protocol's section).

    The machine layer's `MachineConfig` inherits it, with the link's and its own.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    # A registered dialect's name (`names()`): the built-ins, or one a plug-in registered.
    dialect: str = DEFAULT
    # g2core: seconds of silence before the board is asked for a status report; as
    # long again without an answer and the link is taken for dead. grbl: a `?` no
    # report has answered this long is asked again.
    heartbeat: Annotated[float, Field(gt=0)] = 2.0
    # Seconds to wait for the board's banner and the settings after opening.
    handshake_timeout: Annotated[float, Field(gt=0)] = 5.0
    # Status report interval asked of the board, seconds (g2core's minimum is 0.1).
    status_interval: Annotated[float, Field(ge=0.1)] = 0.25

    @field_validator("dialect")
    @classmethod
    def _registered(cls, name: str) -> str:
        lookup(name)  # UnknownDialect (a ValueError) names the registered ones
        return name

    @property
    def spec(self) -> DialectSpec:
        """This machine's dialect, from the registry."""
        return lookup(self.dialect)


class UnknownDialect(ValueError):
    """A name no dialect registered (a config's `dialect`): the known names in the text."""


_registry: dict[str, DialectSpec] = {}
_loaded = False


def register(spec: DialectSpec) -> DialectSpec:
    """Add a dialect; registering the same object again is a no-op, another by a
    taken name a ValueError (a plug-in must not replace a built-in silently)."""
    current = _registry.get(spec.name)
    if current is not None and current is not spec:
        raise ValueError(f"a dialect named {spec.name!r} is already registered")
    _registry[spec.name] = spec
    return spec


def unregister(name: str) -> None:
    """Remove a dialect (a test's own, once it is done)."""
    _registry.pop(name, None)


def _load_builtins() -> None:
    global _loaded
    if not _loaded:
        _loaded = True
        for module in BUILTIN:
            importlib.import_module(module)


def lookup(name: str) -> DialectSpec:
    """The dialect registered as `name` (UnknownDialect naming those there are)."""
    _load_builtins()
    spec = _registry.get(name)
    if spec is None:
        raise UnknownDialect(f"unknown dialect {name!r}: one of {', '.join(names())}")
    return spec


def names() -> Sequence[str]:
    """Every registered dialect's name, sorted."""
    _load_builtins()
    return sorted(_registry)


def load_simulator(spec: DialectSpec) -> Callable[..., object]:
    """The dialect's simulated-board factory, imported now (`simulator` is its path)."""
    module, _, attr = spec.simulator.partition(":")
    factory: Callable[..., object] = getattr(importlib.import_module(module), attr)
    return factory
