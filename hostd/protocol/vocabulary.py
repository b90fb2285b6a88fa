"""The words a session and its caller share: what goes in, what comes out.

A session (session.py, and one per dialect) takes the lines the board
prints and the requests clients make, and gives:
- `data_to_send()`: `(Lane, bytes)` pairs, each one whole line (or realtime
  byte and its LF), in the order they must be written;
- `events()`: what happened, as the dataclasses below;
- `next_deadline()`: the `clock()` time at which `tick()` is due.

Requests carry an opaque token of the caller's (the engine's futures). The
session hands each token back exactly once, in a `Settled` event, with the
controller's answer or the error the request ends in. A job's read
position is the session's own (stream.py): the caller feeds it lines and
reads its counts, and hears its end as a `StreamEnded` event.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from hostd.protocol.classes import CommandClass
from hostd.protocol.errors import MachineError
from hostd.protocol.messages import JsonObject, Response


class Lane(StrEnum):
    """Where a write goes: the engine maps lanes onto the link's channels."""

    DATA = "data"  # a line under the flow control (G-code, `$` text)
    CONTROL = "control"  # a line the board runs on arrival (g2core's `{`-lines)
    REALTIME = "realtime"  # a byte that overtakes everything still on the host


class Phase(StrEnum):
    CLOSED = "closed"  # no link
    HANDSHAKE = "handshake"  # the link is open; the session is learning the board
    READY = "ready"  # clients may use the board


class Context(StrEnum):
    """What a client's line was admitted for; it is written only while that still holds."""

    FREE = "free"  # no job running, no hold: an ordinary line under the window
    HOLD = "hold"  # the board is in a hold: run inside it, in its secondary planner
    JOB = "job"  # an operation runs (a job streaming, settings, a jog): no client action fits
    OPERATION = "operation"  # a line of the running operation itself
    ANY = "any"  # queries and clears: fit every context
    OWN = "own"  # the daemon's own line


class StreamEnd(StrEnum):
    COMPLETED = "completed"
    FAILED = "failed"
    CANCELLED = "cancelled"
    INTERRUPTED = "interrupted"


@dataclass(frozen=True, slots=True)
class StreamResult:
    """How a job's stream ended: its end, and the error code and text of a failure."""

    end: StreamEnd
    code: int | None = None
    message: str | None = None


# -- events ----------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Settled:
    """A request's end: the board's answer, or the error it ends in."""

    token: Any
    outcome: Response | MachineError


@dataclass(frozen=True, slots=True)
class Reported:
    """A status report (automatic, or inside an answer), applied to the model."""

    fields: JsonObject
    snapshot: dict[str, Any]  # the model as this report left it


@dataclass(frozen=True, slots=True)
class Excepted:
    """An exception report, or an answer to no line that reads as one."""

    fields: JsonObject


@dataclass(frozen=True, slots=True)
class Probed:
    report: JsonObject  # as the board printed it
    probe: dict[str, Any]  # the snapshot's `probe`


@dataclass(frozen=True, slots=True)
class Detected:
    """A link or software fault the session saw; the machine's fault table decides."""

    fault: str
    value: Any
    message: str


@dataclass(frozen=True, slots=True)
class Ready:
    """The handshake is done: clients may use the board."""


@dataclass(frozen=True, slots=True)
class Occupied:
    """Found while connecting: the board runs or holds moves it was given before this
    link (a status report says so, and it has not answered the handshake's lines,
    which wait behind them). The handshake waits for them, however long it takes;
    `board_state` is the report's state as the board wrote it."""

    board_state: str
    message: str


@dataclass(frozen=True, slots=True)
class Closing:
    """The session cannot go on over this link (a failed handshake, a reboot, silence).

    `reopen` False: the board may still be moving, and reopening its port could
    reset it mid-motion (an Arduino's DTR): the engine waits to be asked.
    """

    reason: str
    reopen: bool = True


@dataclass(frozen=True, slots=True)
class StreamEnded:
    """The job's stream ended (all answered and the board at rest, or failed, cancelled,
    interrupted): told once, after which the stream's counts only account late answers."""

    job_id: int | None
    result: StreamResult


Event = Settled | Reported | Excepted | Probed | Detected | Ready | Occupied | Closing | StreamEnded


class OwnLine:
    """A mixin for the tokens of a session's own lines: they are never `Settled` out."""


@dataclass(slots=True)
class Queued:
    """A line waiting for a slot: a client's, or the session's own clear."""

    encoded: bytes
    cls: CommandClass
    token: Any
    context: Context

    @property
    def own(self) -> bool:
        return self.context is Context.OWN
