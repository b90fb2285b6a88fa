"""The Engine's lowest layer: its state, declared once, and its one way up.

`Engine` (engine.py) is one class written in layers, a file each, as the
protocol sessions are (docs/architecture.md); this is the lowest. Every field
the engine keeps is declared here, once (`__init__`), so that a reader of any
layer above finds what `self.` holds in one place and mypy --strict checks
every layer against the same declarations. Here too is the engine's one way
up to its Machine (`_up`: the Machine's failure is logged, never let into the
delivery loop), which the console, the link and the delivery loop all use;
the link's states (`LinkState`); and the session the machine's dialect
builds (`session_for`).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from enum import StrEnum
from typing import Any

import structlog

from hostd.link import Link
from hostd.machine.config import MachineConfig
from hostd.machine.events import EngineEvent
from hostd.machine.stream import JobStream
from hostd.protocol.model import MachineModel
from hostd.protocol.session import SessionBase
from hostd.protocol.stream import Stream

log = structlog.get_logger(__name__)


class LinkState(StrEnum):
    DOWN = "down"
    OPENING = "opening"
    HANDSHAKE = "handshake"
    READY = "ready"


class EngineState:
    """The engine's fields and its way up (see `Engine`)."""

    def __init__(
        self, config: MachineConfig, on_event: Callable[[EngineEvent], None] | None = None
    ) -> None:
        self.config = config
        self.id = config.id
        self._on_up: Callable[[EngineEvent], None] = on_event or _ignore  # the way up: one
        self.session = session_for(config)
        self._job: JobStream | None = None  # the job streaming: its file feeds the session
        self.link: Link | None = None
        self.link_state = LinkState.DOWN
        self.console = False  # publish every line sent and received (someone listens)
        # Publish every line but a running job's own and their plain answers (someone
        # listens without them: `job_lines: false`). Without `console` those lines are not
        # even decoded: at a laser's 1,000-2,000 lines/s they were two events a line.
        self.console_but_job = False
        # Publish status polls and reports among those lines (someone listens with them:
        # `status_traffic`, the default). Off, they are not even decoded.
        self.console_status = True
        # The job's `sent` count at the last write: the lines it wrote since are the job's.
        self._sent_stream: Stream | None = None
        self._sent_seen = 0
        self._restart_deadline: float | None = None  # a reset is under way until then
        self._delivering = False  # the delivery loop runs: a nested call leaves it the work
        self._handing_out = False  # events go up now: a command given meanwhile is queued
        self._deferred: list[Callable[[], None]] = []  # run once the events are handed out
        self._write_failed = False
        self._timer: asyncio.TimerHandle | None = None
        self._timer_at: float | None = None
        self._closed: asyncio.Future[str] | None = None  # this connection's end, with why
        self._want = asyncio.Event()
        self._stop = asyncio.Event()
        self._ready = asyncio.Event()
        self._down = asyncio.Event()
        self._down.set()
        self._changed = asyncio.Event()  # pulsed after every step that may change a state
        self._attempt_failed: asyncio.Future[str] | None = None
        self._hold_reopen = False  # the session gave up a board that may move: wait to be asked
        self._log = log.bind(machine=config.id)
        # Whether a line read or written is logged: asked once, not at every line.
        self._traffic_logged = _debug_enabled(self._log)

    @property
    def model(self) -> MachineModel:
        return self.session.model

    def _up(self, event: EngineEvent) -> None:
        """To the Machine; its failure is logged, never let into the delivery loop."""
        try:
            self._on_up(event)
        except Exception:
            self._log.exception("the machine failed on an engine event", kind=type(event).__name__)

    def _broken(self, exc: Exception) -> None:
        """A bug of ours in the session's step: it stops writing; the engine keeps reading."""
        self._log.exception("engine invariant broken")
        self.session.halt(f"{type(exc).__name__}: {exc}")


def _debug_enabled(logger: Any) -> bool:
    """Whether a structlog logger passes debug records (True if it cannot say)."""
    is_enabled_for = getattr(logger, "is_enabled_for", None)
    return True if is_enabled_for is None else bool(is_enabled_for(logging.DEBUG))


def session_for(config: MachineConfig) -> SessionBase:
    """The session of the machine's dialect (its registry entry's): every protocol rule is in it."""
    return config.spec.session(config)


def _ignore(_: EngineEvent) -> None:
    """An engine nobody follows (a test's): its events go nowhere."""
