"""The words a session and its caller share: what goes in, what comes out.

A session (session.py, and one per dialect) takes the lines the board
prints and the requests clients make, and gives:
- `data_to_send()`: `(Lane, bytes)` pairs, each one whole line (or realtime
  byte and its LF), in the order they must be written;
- `events()`: what happened, as the dataclasses below;
- `next_deadline()`: the `clock()` time at which `tick()` is due.

Requests carry an opaque token of the caller's (the engine's futures). The
session hands each token back exactly once, in a `Settled` event, with the
controller's answer or the error the request ends in.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Any, Protocol

from hostd.protocol.classes import CommandClass
from hostd.protocol.errors import MachineError
from hostd.protocol.linemode import InFlight
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


class LineSource(Protocol):
    """A job's lines, pulled only when the flow control has room (machine/stream.py)."""

    job_id: int | None
    exhausted: bool
    paused: bool
    program_pause_sent: bool
    sent: int
    acked: int
    rejected: int
    discarded: int
    last_acked_line: int | None
    line_executed: int | None

    @property
    def done(self) -> bool: ...
    def peek(self) -> InFlight | None:
        """The next line, booked as it will be written (`source` is this stream)."""

    def take(self) -> None: ...
    def prefetch(self) -> None:
        """Get the next lines ready (read, encoded) while the board works: after a write."""

    def acknowledged(self, file_line: int | None) -> None: ...
    def executing(self, file_line: int) -> None:
        """The board says it runs (or has run) this line: a lower bound, kept if higher."""

    def acked_line(self, back: int) -> int | None:
        """The file line of the answered line `back` answers before the last (0: the last)."""

    def finish(self, end: StreamEnd, code: int | None = None, message: str | None = None) -> None:
        """Set the outcome once; later calls are ignored."""


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
class Closing:
    """The session cannot go on over this link (a failed handshake, a reboot, silence).

    `reopen` False: the board may still be moving, and reopening its port could
    reset it mid-motion (an Arduino's DTR): the engine waits to be asked.
    """

    reason: str
    reopen: bool = True


Event = Settled | Reported | Excepted | Probed | Detected | Ready | Closing


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
