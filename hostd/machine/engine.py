"""One machine's engine: the I/O shell around its dialect's session.

The engine holds no protocol rule; the session of the machine's dialect
holds them all. The engine opens the link, feeds the session every line the
board prints and every request a client makes, writes what the session says
to write, runs the one timer the session asks for, and delivers the
session's events: answers to the futures that wait for them, a job's end
to its JobStream, and everything else up to its Machine, through one typed
callback (`on_event`, an `EngineEvent`). The Machine decides what becomes
public (hostd/machine/machine_core.py, `Machine._on_engine`); the engine never
publishes.

Events are delivered only after the step that raised them is over (the
lines of one read; a request taken; a timer). A command the Machine gives
while an event is being handed to it (stopping a job for a fault, marking
an operation) is not run there: it is queued, and
the delivery loop runs it once the whole batch is handed out, then writes
its consequences in the same step. Nothing re-enters the session from
inside its own receive step, nor from inside the delivery of its events.

A job's lines reach the session the same way: after every step the engine
feeds the running job's session position from its file (`JobStream.fill`),
in blocks of up to LOOK_AHEAD lines ahead, and pumps again at once when the
session had room and nothing to send.

A job's steady state takes a shorter way (`_express`, issue 30): a read of
nothing but plain answers to the job's lines, when the job's next plain lines
are all there is to write, is taken, booked and answered with one write by
one call to the session (`express`), without the delivery loop. It is the
same step: the session books what its own loop would, and says None, taking
nothing, whenever that loop could do anything more
(tests/machine/test_fast_path.py runs both and compares).

`serve()` owns the connection for the life of the daemon: it opens the link
when asked (or at once with `auto_connect`), runs one connection until the
link is lost, the session closes it, or a disconnect is asked, tears it down
as one, and reconnects with back-off.

`Engine` is one class written in layers, a file each, as the protocol
sessions are: a layer calls only itself, the layers below it and the
lowest; where a lower layer must reach an upper one it does so through a
hook it declares (raising NotImplementedError) and the upper one implements
(docs/architecture.md, "machine: the engine, an I/O shell"):

  engine_state.py     EngineState     every field (__init__), `_up`, LinkState
  engine_link.py      EngineLink      serve, connect, disconnect, a connection's
                                      opening and teardown; hooks `_deliver`,
                                      `link_lines`
  engine_console.py   EngineConsole   the console: lines published, the job's told
  engine_delivery.py  EngineDelivery  _deliver, _write, _on_event, the timer
  engine_requests.py  EngineRequests  send, realtime, clear, reset, the job's
                                      controls; the views
  engine.py           Engine          reading: link_lines, _receive

This module keeps `Engine` and `LinkState` where every importer finds them.
"""

from __future__ import annotations

from hostd.link import Channel
from hostd.machine.engine_link import RECONNECT_BACKOFF
from hostd.machine.engine_requests import EngineRequests
from hostd.machine.engine_state import LinkState, session_for
from hostd.protocol.vocabulary import Lane

__all__ = ["RECONNECT_BACKOFF", "Engine", "LinkState", "session_for"]


class Engine(EngineRequests):
    """One machine's engine (the module's docstring); this layer reads."""

    # -- reading: the link's callbacks -----------------------------------

    def link_lines(self, channel: Channel, lines: list[bytes]) -> None:
        """Lines as the link read them, in its read callback: no inbox, no task switch.

        A read is one step: every line it holds goes to the session, then what
        they freed is written in one write. (Until issue 30 a read that could
        answer every line the board held wrote the first freed line at once,
        so that the board worked while the daemon read the rest: on a shared,
        unpinned machine that second write woke the board for one line and
        broke the answers into one-line reads, which cost twice the CPU a line;
        docs/performance.md.)
        """
        if self.link is None:
            return  # a read that raced the teardown
        if self._traffic_logged:
            for line in lines:
                self._log.debug("rx", channel=channel.value, line=line)
        try:
            # A job's steady state (`_express`), unless someone listens to the whole
            # console (a listener without the job's lines, the dashboard's, is told none
            # of them) or to the traffic, or a step of several calls is open (`one_step`).
            if not (self.console or self._traffic_logged or self._delivering):
                try:
                    due = self.session.express(lines)
                except Exception as exc:
                    self._broken(exc)  # halted: it writes nothing more, and reads the lines
                    due = None
                if due is not None:
                    self._express(due)
                    return
            if self.console:
                self._receive_published(channel, lines)  # line by line: each is published
            else:
                self._receive(lines, channel if self.console_but_job else None)
            self._deliver()
        except Exception as exc:  # never into the transport's callback: end it
            self._log.exception("engine failure")
            self._end(f"internal error: {exc!r}")

    def _express(self, due: list[bytes]) -> None:
        """The step after a read the session took whole (`express`): the job's next plain
        lines go out in one write, and the job is fed, told and timed as `_deliver`
        would, without its loop. An empty `due`: the rest of the step is the loop's.

        The timer is armed only if none is: no deadline came earlier in this step. The
        read only moved the board's silence later (g2core's heartbeat, grbl's lost
        board), and nothing else changed: no event, no line but the job's, no flush or
        stop under way (`express` says None for each).
        """
        if not due:
            self._deliver()
            return
        link = self.link
        assert link is not None  # link_lines returned early without one
        # A failed write means the link is already gone (see `_write`).
        self._write_failed = not link.write_lines(due)
        if self.console_but_job:  # told as `_write` tells a write (none of the job's)
            self._tx(link, Lane.DATA, due, self._sent_are_job(len(due)))
        job = self._job
        if job is not None:
            if job.fill():  # it had room and nothing ahead, or the file ended: pump again
                self._deliver()
                return
            job.stepped()
        self._changed.set()
        if self._timer is None:
            self._arm_timer()

    def _receive(self, lines: list[bytes], published: Channel | None = None) -> None:
        """The read's lines to the session: each run of plain job answers in one pass
        (`receive_plain`), anything else in full at its place.

        With `published` (someone listens to the console without the job's lines)
        each line taken in full is published as it is, unless it answered a job
        line; the plain answers taken in one pass are the job's, and never are.
        """
        session = self.session
        receive, plain = session.receive, session.receive_plain
        count = len(lines)
        index = 0
        while index < count:
            at = index
            try:
                at = plain(lines, index)
                if at < count:
                    if published is None:
                        receive(lines[at])
                    else:
                        self._receive_one(published, lines[at])
            except Exception as exc:
                self._broken(exc)
            else:
                if at == count:
                    return
            index = at + 1
