"""The Engine's delivery loop: the session's writes, events and timer, step by step.

A layer of `Engine` (engine.py). After every step (the lines of one read, a
request taken, a timer) `_deliver` writes what the session says (`_write`:
consecutive lines of one lane in one write, realtime bytes through the
link's urgent queue), hands out its events (`_on_event`: answers to the
futures that wait for them, a job's end to its JobStream, the link's
readiness and closing to the link's layer, everything else up to the
Machine), feeds the running job from its file, and arms the one timer at the
session's next deadline (`_arm_timer`, `_on_timer`). A command the Machine
gives while it hears the events is queued (`_command`) and run once they all
are handed out; `one_step` makes several calls one step.

This is the per-line path's second half (engine.py's reading is the first):
each method here is the one the single class had, and adds no call.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable, Iterator

from hostd.link import Link
from hostd.machine.engine_console import EngineConsole
from hostd.machine.engine_state import LinkState
from hostd.machine.events import (
    BoardOccupied,
    ExceptionRaised,
    FaultDetected,
    ProbeReported,
    StatusChanged,
)
from hostd.protocol.messages import Response
from hostd.protocol.vocabulary import (
    Closing,
    Detected,
    Event,
    Excepted,
    Lane,
    Occupied,
    Probed,
    Ready,
    Reported,
    Settled,
    StreamEnded,
)


class EngineDelivery(EngineConsole):
    """The delivery loop: writes, events, deferred commands, the timer (see `Engine`)."""

    # -- the delivery loop -----------------------------------------------

    def _deliver(self) -> None:
        """Write what the session says, then hand out its events, until it has nothing more.

        A command the Machine gives while it hears the events (a fault stopping
        a job) waits until they are all handed out; this loop then runs it and
        writes what it adds. After each pass the running job is fed from its file.
        """
        if self._delivering:
            return
        self._delivering = True
        session = self.session
        try:
            while True:
                writes = session.data_to_send()
                events = session.events()
                if writes:
                    self._write(writes)
                if events:
                    self._hand_out(events)
                deferred = self._deferred
                if deferred:  # the Machine's commands, given while it heard the events
                    self._deferred = []
                    for command in deferred:
                        command()
                job = self._job
                # The board is at work on what was written: feed the lines after it. If the
                # session had room and no line, or the file ended, it is pumped again now.
                if job is not None and job.fill():
                    continue
                if not events and not deferred:
                    break  # writing changes nothing in the session: it has no more to say
            job = self._job
            if job is not None:
                job.stepped()
        finally:
            self._delivering = False
            self._handing_out = False
        self._changed.set()
        self._arm_timer()

    @contextlib.contextmanager
    def one_step(self) -> Iterator[None]:
        """Several calls as one step: what they write goes out together, at the end.

        The machine resumes a job and moves its supervisor in one step, so
        that no job line is written, nor published, while it still says paused.
        """
        if self._delivering:
            yield
            return
        self._delivering = True
        try:
            yield
        finally:
            self._delivering = False
            self._deliver()

    def _write(self, writes: list[tuple[Lane, bytes]]) -> None:
        """Consecutive lines of one lane go out in one write (one syscall, not one a line)."""
        link = self.link
        if link is None:
            return
        ok = True
        handed = False
        job = (self.console or self.console_but_job) and self._all_data_is_job(writes)
        batch: list[bytes] = []
        batch_lane: Lane | None = None
        for lane, data in writes:
            if lane is batch_lane:
                batch.append(data)
                continue
            if batch_lane is not None:
                ok = self._write_batch(link, batch_lane, batch, job) and ok
            if lane is Lane.REALTIME:
                ok = link.write_realtime(data) and ok
                # Every realtime byte but the daemon's own status poll: its board reads it
                # before the daemon goes on (`Link.hand_over`), once a write. An operator's
                # hold or override, a fault's stop, and a resume the session kept back
                # until the board stood still, written from a read.
                if not handed and not self.session.status_traffic(data, True):
                    handed = True
                    link.hand_over()
                self._tx(link, lane, [data])
                batch, batch_lane = [], None
            else:
                batch, batch_lane = [data], lane
        if batch_lane is not None:
            ok = self._write_batch(link, batch_lane, batch, job) and ok
        # A failed write means the link is already gone: the lines stay booked,
        # and teardown accounts for them with every other unanswered line.
        self._write_failed = not ok

    def _write_batch(self, link: Link, lane: Lane, lines: list[bytes], job: bool) -> bool:
        ok = link.write_lines(lines, control=lane is Lane.CONTROL)
        if self._traffic_logged or self.console or self.console_but_job:  # `_tx`'s own test
            self._tx(link, lane, lines, job and lane is Lane.DATA)
        return ok

    def _hand_out(self, events: list[Event]) -> None:
        self._handing_out = True
        for event in events:
            self._on_event(event)
        self._handing_out = False

    def _command(self, command: Callable[[], None]) -> None:
        """Run a command of the Machine's now, or, while events are being handed out,
        once they all are (the delivery loop runs it and writes what it says)."""
        if self._handing_out:
            self._deferred.append(command)
            return
        command()
        self._deliver()

    def _on_event(self, event: Event) -> None:
        if isinstance(event, Settled):
            future = event.token
            if not future.done():
                if isinstance(event.outcome, Response):
                    future.set_result(event.outcome)
                else:
                    future.set_exception(event.outcome)
        elif isinstance(event, Reported):
            self._up(StatusChanged(self.id, event.fields, event.snapshot))
        elif isinstance(event, StreamEnded):
            job = self._job
            if job is not None and job.position.done:
                self._job = None
                job.ended(event.result)
        elif isinstance(event, Excepted):
            self._up(ExceptionRaised(self.id, event.fields))
        elif isinstance(event, Detected):
            self._up(FaultDetected(self.id, event.fault, event.value, event.message))
        elif isinstance(event, Occupied):
            # A connect waiting for the handshake learns why it waits, and the link stays
            # open: the handshake goes on until the board is through (or stopped).
            self._end_attempt(event.message)
            self._up(BoardOccupied(self.id, event.board_state))
        elif isinstance(event, Probed):
            self._up(ProbeReported(self.id, event.report, event.probe))
        elif isinstance(event, Ready):
            self._on_ready()
        elif isinstance(event, Closing):
            if not event.reopen:
                # The board may be moving: reopening its port could reset it (an Arduino's
                # DTR). Only a connect asked for (machine.connect) opens it again.
                self._log.warning("link given up; not reopened on its own", reason=event.reason)
                self._want.clear()
                self._hold_reopen = True
            self._end(event.reason)

    def _arm_timer(self) -> None:
        """One timer, at the session's next deadline; an early wake-up is harmless."""
        deadline = self.session.next_deadline()
        if deadline is None or (self._timer_at is not None and self._timer_at <= deadline):
            return
        if self._timer is not None:
            self._timer.cancel()
        delay = max(0.0, deadline - time.monotonic())
        self._timer = asyncio.get_running_loop().call_later(delay, self._on_timer)
        self._timer_at = deadline

    def _on_timer(self) -> None:
        self._timer = self._timer_at = None
        if self.link_state is LinkState.DOWN:
            return
        try:
            self.session.tick()
        except Exception as exc:
            self._broken(exc)
        self._deliver()
