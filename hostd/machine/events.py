"""What an engine tells its Machine, what a Machine publishes, and the hub that hands it out.

Two ways, each one-way. An engine reports to its Machine alone, through one
typed callback (`EngineEvent`); the Machine publishes facts to the hub
(`Event`), in causal order: a status report before the supervisor change
and the faults it caused. `FaultDetected` is the engine's word to its
Machine, never public: the Machine's fault table decides what it becomes
(a `FaultChanged`).

Publishing is synchronous and must stay cheap: a subscriber's callback only
queues (the API's per-client queues are bounded; what happens at the bound
is theirs to decide). A failing callback is logged and dropped, never
allowed to break the machine that published.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import structlog

from hostd.protocol.messages import JsonObject

log = structlog.get_logger(__name__)


@dataclass(frozen=True, slots=True)
class StatusChanged:
    machine: str
    report: JsonObject
    snapshot: dict[str, Any]


@dataclass(frozen=True, slots=True)
class ExceptionRaised:
    machine: str
    report: JsonObject


@dataclass(frozen=True, slots=True)
class ProbeReported:
    machine: str
    report: JsonObject  # as the board printed it
    probe: dict[str, Any]  # the snapshot's `probe`: {"ok", "position"}


@dataclass(frozen=True, slots=True)
class Console:
    machine: str
    direction: str  # "tx" | "rx"
    channel: str  # "data" | "control"
    text: str
    # A running job's own line, or a board's plain answer (status 0) to one: what a
    # subscription with `job_lines: false` leaves out (docs/api.md).
    job: bool = False
    # A status poll or report (`SessionBase.status_traffic`): what a subscription with
    # `status_traffic: false` leaves out.
    status: bool = False


@dataclass(frozen=True, slots=True)
class LinkChanged:
    machine: str
    up: bool
    reason: str


@dataclass(frozen=True, slots=True)
class SupervisorChanged:
    machine: str
    source: str
    target: str
    event: str


@dataclass(frozen=True, slots=True)
class JobChanged:
    machine: str
    job: dict[str, Any]


@dataclass(frozen=True, slots=True)
class FaultDetected:
    """The engine saw a link or software fault; the machine's fault table decides.

    Told to the Machine only (an `EngineEvent`): it publishes the `FaultChanged`.
    """

    machine: str
    fault: str
    value: Any
    message: str


@dataclass(frozen=True, slots=True)
class BoardOccupied:
    """Found while connecting: the board runs or holds moves it was given before this
    link, and the handshake waits for them (the session's `Occupied`; the operator
    is told by its `ExceptionRaised`). Told to the Machine only (an `EngineEvent`):
    after `ran_unwatched` it stops the board."""

    machine: str
    board_state: str


@dataclass(frozen=True, slots=True)
class FaultChanged:
    machine: str
    fault: dict[str, Any]


# What an engine tells its Machine (hostd/machine/engine.py `on_event`).
EngineEvent = (
    StatusChanged
    | ExceptionRaised
    | ProbeReported
    | Console
    | LinkChanged
    | FaultDetected
    | BoardOccupied
)
# What a Machine publishes to the hub's subscribers (the API, MQTT, systemd's status).
Event = (
    StatusChanged
    | ExceptionRaised
    | ProbeReported
    | Console
    | LinkChanged
    | SupervisorChanged
    | JobChanged
    | FaultChanged
)
Listener = Callable[[Event], None]


class Hub:
    def __init__(self) -> None:
        self._listeners: list[Listener] = []

    def subscribe(self, listener: Listener) -> Callable[[], None]:
        self._listeners.append(listener)
        return lambda: self._listeners.remove(listener)

    @property
    def active(self) -> bool:
        return bool(self._listeners)

    def publish(self, event: Event) -> None:
        for listener in list(self._listeners):
            try:
                listener(event)
            except Exception:
                log.exception("listener failed; removed", kind=type(event).__name__)
                self._listeners.remove(listener)
