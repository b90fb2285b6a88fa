"""The steady read: a job's steady state in one pass (issue 30), a layer of every session.

While a job streams and nothing else happens, almost every read the board
gives is the answers to the job's oldest lines, and almost every write is the
job's next lines. `SteadyRead` takes such a read without the general path's
line-by-line reading: `receive_plain` takes each run of plain job answers in
one pass, and `express` takes a whole read of them and hands back the job's
next plain lines for one write (the engine's express step,
hostd/machine/engine.py). Everything else, and any read in which something
else happens, goes through `receive` and the dialect's `_pump`.

A dialect gives the four words this layer asks: `_take_answers` (its plain
answers, taken in bulk), `_writes_wait` and `_job_lines_wait` (the same gate
its `_pump` asks, so the two paths can never write different lines), and
`_take_run` (the lines its flow control has room for, taken and booked).
`SessionBase` (session.py) sets the state read here.
"""

from __future__ import annotations

from collections import deque

from hostd.protocol.linemode import InFlight
from hostd.protocol.model import MachineModel
from hostd.protocol.states import MachineState
from hostd.protocol.stream import Stream
from hostd.protocol.vocabulary import Event, Lane, Phase, Queued


class SteadyRead:
    """A job's steady state read and written in bulk (see the module's docstring)."""

    # The session's state this layer reads, set by `SessionBase.__init__`.
    stream: Stream | None
    phase: Phase
    halted: bool
    model: MachineModel
    _out: list[tuple[Lane, bytes]]
    _events: list[Event]
    _outbox: deque[Queued]

    # Off, every line takes the general path: the property tests compare the two
    # (tests/machine/test_fast_path.py).
    fast_path = True

    def receive_plain(self, lines: list[bytes], start: int) -> int:
        """Take `lines` from `start` on, in one pass, while each is a plain answer to the
        running job's oldest line (what `receive` would do with it, done in bulk); the
        index of the first line left, which the caller gives to `receive`. A dialect
        without this fast path takes none."""
        stream = self._steady_stream()
        if stream is None:
            return start
        return self._take_answers(lines, start, stream)

    def _take_answers(
        self, lines: list[bytes], start: int, stream: Stream, *, whole: bool = False
    ) -> int:
        """The dialect's: `receive_plain`'s pass over the lines from `start` on, the job's
        position given; with `whole`, all of them or none (`express`)."""
        return start

    def express(self, lines: list[bytes]) -> list[bytes] | None:
        """A job's steady state in one call (the engine's express step, issue 30): a read
        of nothing but plain answers to the job's oldest lines, at a time when nothing
        but the job's next plain lines is to be written (no event, no other line
        waiting, the job in its steady state, nothing the dialect holds its writes
        for). Every answer is taken, then the job's next plain lines that the flow
        control has room for, taken and booked, are returned for one write: the
        writer's loop, run after them, would write nothing more and change nothing.

        None, and nothing taken, otherwise: the engine reads the lines in full and
        runs its delivery loop. An empty list: the answers are taken, and the rest
        of the step is the delivery loop's (the run stopped short of its room, at a
        line the writer's loop must look at, which `data_to_send` hands out after
        what this took; or nothing fitted). Plain answers change none of the
        conditions, so they are checked before the answers are taken.
        """
        stream = self._steady_stream()
        if (
            stream is None
            or self.phase is not Phase.READY
            or self.halted
            or self._outbox
            or self._out
            or self._events
            or self._writes_wait()
            or self._job_lines_wait(stream, self.model.state)
            or not self._take_answers(lines, 0, stream, whole=True)  # 0: none taken
        ):
            return None
        taken = self._take_run(stream)
        due = [entry.line for entry in taken]
        if not stream.full:  # the writer's loop goes on from there: the general step
            data = Lane.DATA
            self._out.extend([(data, line) for line in due])
            return []
        return due

    def _writes_wait(self) -> bool:
        """The dialect's: it writes nothing now, or only what its own loop must see (a
        flush awaiting its proof, a line writing EEPROM, a client's query waiting)."""
        return True

    def _job_lines_wait(self, stream: Stream, state: MachineState | None) -> bool:
        """The dialect's: none of the job's lines may be written now (`_pump`'s test)."""
        return True

    def _take_run(self, stream: Stream) -> list[InFlight]:
        """The dialect's: the job's plain lines ahead that its flow control has room for,
        taken and booked (`Stream.take_run`); asked only once `_writes_wait` and
        `_job_lines_wait` said no."""
        raise NotImplementedError

    def _steady_stream(self) -> Stream | None:
        """The running job, if its answers may take the fast path: not at its end (its
        input ended, or a refused line's turn came: each answer then checks whether the
        job is complete)."""
        stream = self.stream
        if (
            stream is None
            or stream.done
            or stream.input_ended
            or stream.refused is not None
            or not self.fast_path
        ):
            return None
        return stream
