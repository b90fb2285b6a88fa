"""The Engine's console: which lines written and read are published, and how.

A layer of `Engine` (engine.py). A `Console` event is made for a line only
while someone listens (`console`), or listens without a running job's own
lines and the board's plain answers to them (`console_but_job`); status
polls and reports among them (`SessionBase.status_traffic`, asked of a line read
before the session takes it) only with `console_status`. Whether a line is
the job's is told from the job's own counts: its `sent` moved by exactly the
write's data lines (`_all_data_is_job`), its `acked` moved by one as the
answer was read (`_receive_one`). A line read is published after the session
took it, a line written as it goes out (`_tx`, which also keeps the debug
record of the traffic).

Nothing here is on a job's per-line path unless someone listens: the reading
(engine.py) and the writes (engine_delivery.py) test the flags first.
"""

from __future__ import annotations

from hostd.link import Channel, Link
from hostd.machine.engine_link import EngineLink
from hostd.machine.events import Console
from hostd.protocol.vocabulary import Lane


class EngineConsole(EngineLink):
    """Console routing: the lines published, and whether each is the job's (see `Engine`)."""

    def _receive_published(self, channel: Channel, lines: list[bytes]) -> None:
        """`receive` for each line, each published as a console event after it is taken."""
        for line in lines:
            self._receive_one(channel, line)

    def _receive_one(self, channel: Channel, line: bytes) -> None:
        """`receive` for one line, then its console event: after, so that the job's
        count says whether the line was the plain answer (status 0) to one of the
        job's lines (the stream's `acked` moved by one). The event still goes out
        before any the line caused (those are handed out once the whole read is
        taken)."""
        session = self.session
        stream = session.stream
        acked = stream.acked if stream is not None else 0
        # Asked before the line is taken: an answer is the session's own poll's only
        # while that poll is still unanswered (grbl's `$G`, `status_traffic`).
        status = session.status_traffic(line, False)
        try:
            session.receive(line)
        except Exception as exc:
            self._broken(exc)
        job = stream is not None and stream.acked == acked + 1
        if job and not self.console:
            return
        self._publish_console("rx", channel, line, job, status and not job)

    def _all_data_is_job(self, writes: list[tuple[Lane, bytes]]) -> bool:
        """Whether every data-lane line of these writes is a line of the running job.

        The job's `sent` count moves when the session books a job line for writing,
        so the lines it moved by since the last write are the job's. Only when they
        are all the data lines here (no query admitted among them) are they called
        the job's; otherwise all are shown: leaving out too little is harmless.
        """
        return self._sent_are_job(sum(1 for lane, _ in writes if lane is Lane.DATA))

    def _sent_are_job(self, data_lines: int) -> bool:
        """`_all_data_is_job` for a write of `data_lines` data lines."""
        stream = self.session.stream
        if stream is None:
            self._sent_stream = None
            return False
        sent = stream.sent
        before = self._sent_seen if self._sent_stream is stream else 0
        self._sent_stream, self._sent_seen = stream, sent
        if sent == before:
            return False
        return sent - before == data_lines

    def _tx(self, link: Link, lane: Lane, lines: list[bytes], job: bool = False) -> None:
        if not (self._traffic_logged or self.console or self.console_but_job):
            return
        if self._traffic_logged:  # else only the console listens: no debug record is kept
            if lane is Lane.DATA and len(lines) > 1:
                self._log.debug("tx", lane=lane.value, lines=len(lines))  # a job's window
            else:
                for line in lines:
                    self._log.debug("tx", lane=lane.value, line=line)
        if self.console or (self.console_but_job and not job):
            channel = Channel.CONTROL if lane is not Lane.DATA and link.dual else Channel.DATA
            status = self.session.status_traffic
            for line in lines:
                self._publish_console("tx", channel, line, job, not job and status(line, True))

    def _publish_console(
        self, direction: str, channel: Channel, line: bytes, job: bool, status: bool
    ) -> None:
        """A `Console` event for a line, unless it is status traffic (`status`: the
        session's word, never said of a job's line) and no console subscriber wants it."""
        if status and not self.console_status:
            return
        text = line.rstrip(b"\n").decode("utf-8", "backslashreplace")
        self._up(Console(self.id, direction, str(channel), text, job, status))
