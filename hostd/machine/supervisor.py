"""The per-machine supervisor (conveyor's machine thread, seed 004): one table.

Everything that moves the supervisor lives here. An event that does not fit
the current state is refused whole (`Refused`, error 1003 at the API); the
state is never half-changed. Every transition is handed to the listeners.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum


class State(StrEnum):
    DISCONNECTED = "disconnected"
    BUSY = "busy"
    IDLE = "idle"
    OPERATION = "operation"
    PAUSED = "paused"


class Event(StrEnum):
    CONNECT = "connect"
    DISCONNECT = "disconnect"  # asked for
    DISCONNECTED = "disconnected"  # lost
    WENT_IDLE = "went-idle"
    WENT_BUSY = "went-busy"
    START_OPERATION = "start-operation"
    PAUSE_OPERATION = "pause-operation"
    UNPAUSE_OPERATION = "unpause-operation"
    OPERATION_STOPPED = "operation-stopped"


_CONNECTED = (State.BUSY, State.IDLE, State.OPERATION, State.PAUSED)

# (from, event) -> to. behaviour.md "Supervisor"; seed 004 "Went Busy" may
# come from any connected state, which the board's own activity shows as
# busy only while no host operation runs (idle -> busy).
TRANSITIONS: dict[tuple[State, Event], State] = {
    (State.DISCONNECTED, Event.CONNECT): State.BUSY,
    **{(s, Event.DISCONNECT): State.DISCONNECTED for s in _CONNECTED},
    **{(s, Event.DISCONNECTED): State.DISCONNECTED for s in _CONNECTED},
    (State.BUSY, Event.WENT_IDLE): State.IDLE,
    (State.IDLE, Event.WENT_BUSY): State.BUSY,
    (State.IDLE, Event.START_OPERATION): State.OPERATION,
    (State.OPERATION, Event.PAUSE_OPERATION): State.PAUSED,
    (State.PAUSED, Event.UNPAUSE_OPERATION): State.OPERATION,
    (State.OPERATION, Event.OPERATION_STOPPED): State.BUSY,
    (State.PAUSED, Event.OPERATION_STOPPED): State.BUSY,
}


class Refused(Exception):
    """The event does not fit the current state."""

    code = 1003

    def __init__(self, state: State, event: Event) -> None:
        super().__init__(f"cannot {event.value} while {state.value}")
        self.state = state
        self.event = event
        self.message = str(self)


@dataclass(frozen=True, slots=True)
class Transition:
    source: State
    target: State
    event: Event


Listener = Callable[[Transition], None]


class Supervisor:
    def __init__(self, listener: Listener | None = None) -> None:
        self.state = State.DISCONNECTED
        self._listener = listener

    def can(self, event: Event) -> bool:
        return (self.state, event) in TRANSITIONS

    def fire(self, event: Event) -> Transition:
        """Take the transition, or raise Refused and change nothing."""
        target = TRANSITIONS.get((self.state, event))
        if target is None:
            raise Refused(self.state, event)
        transition = Transition(self.state, target, event)
        self.state = target
        if self._listener is not None:
            self._listener(transition)
        return transition
