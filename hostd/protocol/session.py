"""What every dialect's session shares: `SessionBase`, the rules behaviour.md asks of all.

A session is a controller's protocol without I/O, in the manner of h11's
`Connection`: the engine feeds it the lines the board prints and the
requests clients make, and takes from it the bytes to write, the events to
deliver and the next moment it wants to be woken. It never reads a port,
never sleeps and never calls back into its caller: every decision is made
on a call and every consequence leaves as output. Its inputs and outputs,
and the words for both, are in vocabulary.py.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Any

import structlog

from hostd.protocol.classes import CommandClass, classify_realtime
from hostd.protocol.commands import InvalidCommand, Realtime, Refusal
from hostd.protocol.errors import Busy, FaultActive, MachineError, NotConnected, Rejected
from hostd.protocol.messages import Response
from hostd.protocol.model import MachineModel
from hostd.protocol.states import MachineState
from hostd.protocol.steady import SteadyRead
from hostd.protocol.stream import Stream
from hostd.protocol.vocabulary import (
    Closing,
    Context,
    Detected,
    Event,
    Lane,
    OwnLine,
    Phase,
    Queued,
    Settled,
    StreamEnd,
    StreamEnded,
)
from hostd.protocol.words import Words

log = structlog.get_logger(__name__)


class SessionBase(SteadyRead, Words):
    """The rules of behaviour.md that hold over every dialect; a dialect fills in the rest.

    A dialect gives: `_admit` (its command class table), `_pump` (its flow
    control), `_query_status`, `_stop_board` (a fault's stop), `_realtime`
    (how a realtime command goes on its wire), `flushing`, `no_data_in_flight`
    and `unanswered`; the steady read's four words (`SteadyRead`, steady.py:
    `_take_answers`, `_writes_wait`, `_job_lines_wait`, `_take_run`); its words
    for jobs, jogs and settings (`Words`, words.py: `encode_job_line`,
    `jog_lines`, `settings_*`, ...); and it
    takes the board's lines, the timers and the requests that differ
    (`receive`, `tick`, `next_deadline`, `send`, `clear`, `reset`, `open`,
    `close`).
    """

    def __init__(self, machine_id: str, clock: Callable[[], float]) -> None:
        self.id = machine_id
        self.clock = clock
        self.model = MachineModel(machine_id)
        self.phase = Phase.CLOSED
        self.stream: Stream | None = None  # the job's read position: the session's own
        self.halted = False  # an internal fault: nothing but halts and reset is written
        self._out: list[tuple[Lane, bytes]] = []
        self._events: list[Event] = []
        self._outbox: deque[Queued] = deque()  # lines under the flow control, in order
        self._lane: deque[Queued] = deque()  # lines that go past it (queries, in-hold lines)
        self._await_report = False  # an exception came: actions and job lines wait for a report
        self._awaiting_rest = False  # the job is answered: waiting for the board to stop
        self._operation = False  # the machine runs an operation: client actions are busy
        # `~` went out: the hold is ending, whatever the last report says, so no line is
        # admitted into it any more, until the board shows a state other than HOLD and
        # other than the one it was in when the `~` went (`_resumed_from`), or a new `!`.
        self._resuming = False
        self._resumed_from: MachineState | None = None
        self._closing_reason: str | None = None  # asked to be closed: nothing more is due
        # How many `override` requests the board has answered: machine.override waits
        # for the next one, then answers `model.overrides` (the board's own values).
        self.override_answers = 0
        self._log = log.bind(machine=machine_id)

    # -- what a dialect gives --------------------------------------------------

    def _admit(self, cls: CommandClass, state: MachineState | None) -> int | None:
        raise NotImplementedError

    def _pump(self) -> None:
        raise NotImplementedError

    def _query_status(self) -> None:
        raise NotImplementedError

    def query_status(self) -> None:
        """Ask the board for a full status report now."""
        self._query_status()

    def _stop_board(self) -> None:
        raise NotImplementedError

    def _at_rest(self) -> bool:
        """The board has run everything it was given (a dialect may know more than its state)."""
        return self.model.state is not None and self.model.state.is_resting

    def flushing(self) -> bool:
        """A stop is under way whose outcome the board has not shown yet."""
        raise NotImplementedError

    def no_data_in_flight(self) -> bool:
        raise NotImplementedError

    def unanswered(self) -> int:
        """Lines written and not answered yet, of every kind."""
        raise NotImplementedError

    def realtime(self, command: Realtime) -> None:
        """Write a realtime command now (it never waits), if the state admits it."""
        self._require_open()
        cls = classify_realtime(command)
        verdict = self._admit(cls, self.model.state)
        if verdict is not None:
            raise Rejected(verdict, self._locked_message())
        if self.halted and cls not in (CommandClass.HALT, CommandClass.RESET):
            raise self._write_refused()
        if command is Realtime.CYCLE_START:
            self._end_hold_admission()
        elif command is Realtime.FEEDHOLD:
            self._resuming = False  # a hold of ours begins: lines may run inside it again
        self._realtime(command)

    def _end_hold_admission(self) -> None:
        """The `~` and the end of in-hold admission are one step (issue 24, part 5).

        In-hold lines already admitted are written now, ahead of the `~`, while the
        board still holds; those that cannot go now (no room) fail. From here on no
        line is admitted into the hold, even while reports still say HOLD (the board
        has not read the `~` yet): a line written after the `~` must never carry the
        hold's context.
        """
        self._pump()
        self._resuming = True
        self._resumed_from = self.model.state
        self._recheck_waiting()

    def _realtime(self, command: Realtime) -> None:
        """The dialect's bytes for an admitted realtime command."""
        raise NotImplementedError

    # -- what a dialect takes --------------------------------------------------

    def open(self, *, rebooting: bool = False) -> None:
        """The link is open: begin the handshake (after a reset the board's banner is due)."""
        raise NotImplementedError

    def close(self, reason: str, *, restarted: bool = False) -> None:
        """The link is gone: settle every line and request it carried."""
        raise NotImplementedError

    def receive(self, line: bytes) -> None:
        """One line the board printed (without its line end)."""
        raise NotImplementedError

    def status_traffic(self, line: bytes, written: bool) -> bool:
        """Whether a line written (`written`) or read is status traffic: the host's own
        status poll, or a status report. Several a second on every machine, and read from
        the `status` topic's snapshots rather than the console: a `console` subscription
        with `status_traffic: false` leaves them out (docs/api.md)."""
        return False

    def line_running(self) -> int | None:
        """The file line the board's last report says it is executing, where its dialect
        can tell (docs/api.md, "How exact `line_executed` is"); None where it cannot.
        Asked of a board found moving with no job of ours streaming (machine_core.py
        `_stop_unwatched`)."""
        return None

    def tick(self) -> None:
        """A deadline passed (or the engine woke early: nothing is due then)."""
        raise NotImplementedError

    def next_deadline(self) -> float | None:
        raise NotImplementedError

    def send(self, line: str, token: Any, *, operation: bool = False) -> None:
        """One line from a client; its answer or error comes back as `Settled(token, ...)`."""
        raise NotImplementedError

    def clear(self, token: Any) -> bool:
        """Leave a lockout the way the board allows; False if there is nothing to clear."""
        raise NotImplementedError

    def reset(self) -> None:
        """0x18: the board restarts; so do the session's books."""
        raise NotImplementedError

    def modes_pending(self) -> bool:
        """A poll of the board's modes is in flight whose answer the model will take (grbl's
        `$G` after a client's line: its units and distance mode are reported nowhere
        else). False where the reports carry them."""
        return False

    def occupied(self) -> dict[str, str] | None:
        """While connecting: the board was found busy with moves it was given before
        this link, and the handshake waits for them (`{"state", "message"}`); None
        otherwise. A dialect whose handshake passes while its board runs never is."""
        return None

    def lockout(self) -> dict[str, str] | None:
        """The lockout the board is in, in words an operator acts on; None outside one.

        `state` is the common state's name, `message` what the board said caused it,
        `clear` the API methods that end it, in order. A dialect whose board is
        cleared another way says so by overriding `_lockout_exit`.
        """
        state = self.model.state
        if state is None or not (state.is_lockout or state is MachineState.INTERLOCK):
            return None
        return {
            "state": state.name,
            "message": self.model.last_exception_message() or state.name.lower(),
            "clear": self._lockout_exit(state),
        }

    def _lockout_exit(self, state: MachineState) -> str:
        """g2core's rules (seed 000): {clear} ends ALARM and SHUTDOWN, only 0x18 a PANIC."""
        if state is MachineState.PANIC:
            return "machine.reset"
        if state is MachineState.INTERLOCK:
            return "close the interlock, then machine.cycle_start"
        return "machine.clear"

    def override(
        self, feed: int | None = None, rapid: int | None = None, spindle: int | None = None
    ) -> None:
        """Set the feed, rapid and spindle overrides (percent) now, in any state.

        The dialect then asks what is in force, and counts `override_answers` up once
        the board has said (into `model.overrides`).
        """
        raise InvalidCommand(
            Refusal.UNREADABLE, f"{self.id}: this controller's dialect has no realtime overrides"
        )

    def safety_door(self) -> None:
        """The host opens the safety door: the board holds, and parks if it is set to."""
        raise InvalidCommand(
            Refusal.UNREADABLE, f"{self.id}: this controller's dialect has no safety-door command"
        )

    # -- outputs ---------------------------------------------------------------

    def data_to_send(self) -> list[tuple[Lane, bytes]]:
        """Everything to write now, in order (the waiting lines that fit are taken first)."""
        self._pump()
        out, self._out = self._out, []
        return out

    def events(self) -> list[Event]:
        events, self._events = self._events, []
        return events

    @property
    def ready(self) -> bool:
        return self.phase is Phase.READY

    def _closing(self, reason: str, *, reopen: bool = True) -> None:
        if self._closing_reason is None:
            self._closing_reason = reason
            self._events.append(Closing(reason, reopen))

    def _context(self) -> Context:
        if self.model.state is MachineState.HOLD and not self._resuming:
            return Context.HOLD
        return Context.JOB if self._job_running() or self._operation else Context.FREE

    def set_operation(self, running: bool) -> None:
        """The machine started or ended an operation; waiting client actions are judged again."""
        self._operation = running
        self._recheck_waiting()

    def _admissible(self, queued: Queued, state: MachineState | None, context: Context) -> bool:
        """May this waiting line be written now? If not, its asker is told why, once."""
        verdict = self._admit(queued.cls, state)
        if verdict is not None:
            self._settle(queued.token, Rejected(verdict, self._locked_message()))
            return False
        if queued.context in (Context.ANY, Context.OWN) or queued.context is context:
            return True
        if queued.context is Context.OPERATION and self._operation:
            return True
        self._settle(queued.token, Busy(_context_changed(self.id, queued.context, context)))
        return False

    def _recheck_waiting(self) -> None:
        """After any change of context, fail the waiting lines it no longer admits.

        Not while a flush is under way: the board passes through a hold on its
        way to the stop that ends it, and nothing is written before then, so
        the write itself decides.
        """
        state = self.model.state
        if self._resuming and state is not MachineState.HOLD and state is not self._resumed_from:
            self._resuming = False  # the board shows the hold ended
        if self.flushing():
            return
        state, context = self.model.state, self._context()
        self._outbox = deque(q for q in self._outbox if self._admissible(q, state, context))
        self._lane = deque(q for q in self._lane if self._admissible(q, state, context))

    def _settle(self, token: Any, outcome: Response | MachineError) -> None:
        if not isinstance(token, OwnLine):
            self._events.append(Settled(token, outcome))

    def _check_stream_complete(self, *, reported: bool = False) -> None:
        """{r} means queued, not run: a job is done when all is answered and the board rests.

        Only a report read after the last answer can say it rests (`reported`):
        the state known before may be from before the job's moves began.
        """
        stream = self.stream
        if stream is None or stream.done:
            return
        if stream.refused is not None:  # a line the board must never receive: its turn came
            number, why = stream.refused
            self._end_stream(stream, StreamEnd.FAILED, -32602, f"line {number}: {why}")
            return
        if not stream.exhausted or stream.acked < stream.sent:
            return
        if not self._awaiting_rest:
            self._awaiting_rest = True
            self._query_status()  # its answer, or any later report, tells whether it rests
            return
        # At rest: PROGRAM_STOP or PROGRAM_END, or READY for a job that never moved it.
        if reported and self._at_rest():
            self._awaiting_rest = False
            self._end_stream(stream, StreamEnd.COMPLETED)

    def _end_stream(
        self, stream: Stream, end: StreamEnd, code: int | None = None, message: str | None = None
    ) -> None:
        """The job ends, once: its outcome is set, and told as `StreamEnded`."""
        if stream.finish(end, code, message):
            assert stream.result is not None
            self._events.append(StreamEnded(stream.job_id, stream.result))

    def _require_ready(self) -> None:
        if self.phase is not Phase.READY:
            raise NotConnected(f"{self.id} is not connected")

    def _require_open(self) -> None:
        """The link is open (a realtime byte may go even while the handshake runs)."""
        if self.phase is Phase.CLOSED:
            raise NotConnected(f"{self.id} is not connected")

    def _end_stream_on_close(self, reason: str, restarted: bool) -> None:
        """The link is gone: a live job ends failed if the board was reset, else interrupted."""
        stream = self.stream
        if stream is not None:
            if restarted:
                self._end_stream(stream, StreamEnd.FAILED, 1005, "the controller was reset")
            else:
                self._end_stream(stream, StreamEnd.INTERRUPTED, 1002, f"link lost: {reason}")

    def _drain_for_lockout(self, state: MachineState, describe: Callable[[int], str]) -> None:
        """A lockout: the running job ends failed with the lockout's code, and its remaining
        lines are dropped on the host at once. `describe` names the code when the board
        said nothing of its own."""
        refusal = self._admit(CommandClass.ACTION, state)
        if refusal is not None and self.stream is not None and not self.stream.done:
            text = self.model.last_exception_message() or describe(refusal)
            self._end_stream(self.stream, StreamEnd.FAILED, int(refusal), text)

    def cancel(self, token: Any) -> None:
        """The asker gave up: a line not yet written is not written."""
        self._outbox = deque(q for q in self._outbox if q.token is not token)
        self._lane = deque(q for q in self._lane if q.token is not token)

    def admit_action(self) -> None:
        """Rejected (204/205/206) if an action may not reach the board now."""
        verdict = self._admit(CommandClass.ACTION, self.model.state)
        if verdict is not None:
            raise Rejected(verdict, self._locked_message())

    def start_stream(self, stream: Stream) -> None:
        """Stream this job: its lines go as the flow control has room, as they are fed."""
        self._require_ready()
        if self._job_running():
            raise Busy(f"{self.id} is running a job")
        self.admit_action()
        self.stream = stream
        self._awaiting_rest = False
        self._recheck_waiting()  # a client line still waiting was not admitted into a job

    def pause_stream(self) -> None:
        """The job's pause: `!`, and none of its lines is written until `resume_stream`."""
        stream = self._live_stream()
        self.realtime(Realtime.FEEDHOLD)
        stream.paused = True

    def resume_stream(self) -> None:
        """The job's resume: `~`, and its lines flow again."""
        stream = self._live_stream()
        if not stream.paused:
            raise Busy(f"{self.id}: the job is not paused")
        self.realtime(Realtime.CYCLE_START)
        stream.paused = False

    def release_stream(self, tool: int | None = None) -> None:
        """Pass the job's hold point (stream.py: a tool change the operator answered): the
        line it kept back goes as the flow control has room, unless the job is paused.

        `tool`: the tool the operator put in (the M6's T), the snapshot's `tool` from now
        on. A board may not know it: grbl is sent the M6 line without its M6, and
        grblHAL then keeps the T as pending (core gcode.c "[5. Select tool ]"), its `$G`
        still naming the old tool. A later report of the board's own tool still wins."""
        stream = self._live_stream()
        if stream.held is None:
            raise Busy(f"{self.id}: the job is not held")
        stream.release()
        if tool is not None:
            self.model.tool = tool

    def stop_stream(self, code: int, text: str) -> None:
        """Fail the running job and stop the board: feedhold, then flush (a fault's effect)."""
        if self.stream is None or self.stream.done:
            return
        self._end_stream(self.stream, StreamEnd.FAILED, code, text)
        if self.phase is not Phase.CLOSED:
            self._stop_board()

    def interrupt_stream(self, code: int, text: str) -> None:
        """The daemon stops during the job: it ends interrupted, and the board is stopped
        as a cancel stops it (the dialect's job kill: it holds, drops what it holds, and
        turns the spindle off), so that it neither runs the job's lines unwatched nor
        stands with the spindle or beam on (docs/operations.md, "When the daemon stops")."""
        if self.stream is None or self.stream.done:
            return
        self._end_stream(self.stream, StreamEnd.INTERRUPTED, code, text)
        if self.phase is not Phase.CLOSED:
            self.realtime(Realtime.JOB_KILL)  # admitted as a cancel's is

    def halt(self, text: str) -> None:
        """The daemon broke one of its own invariants: write nothing more until reset."""
        self.halted = True
        if self.stream is not None and not self.stream.done:
            self._end_stream(
                self.stream, StreamEnd.FAILED, FaultActive.code, f"internal fault: {text}"
            )
        self._detected("internal", None, text)

    def _live_stream(self) -> Stream:
        stream = self.stream
        if stream is None or stream.done:
            raise Busy(f"{self.id} has no job streaming")
        return stream

    def out_of_hold(self) -> bool:
        """No hold on the board and no flush under way: a free line is written as it is."""
        return not self.flushing() and self.model.state is not MachineState.HOLD

    def locked(self) -> bool:
        state = self.model.state
        return state is not None and state.is_lockout

    def _job_running(self) -> bool:
        return self.stream is not None and not self.stream.done

    def quiet(self) -> bool:
        """Nothing of the host's queued or unanswered, but for queries, and no stop of
        the host's under way (a job's failure stops and empties the board: until the
        board shows it did, a line sent would be thrown away with what it held)."""
        return (
            not self._outbox
            and self.no_data_in_flight()
            and not self._job_running()
            and not self.flushing()
        )

    # -- helpers -----------------------------------------------------------------

    def _job_log(self) -> Any:
        """The machine's logger, with `job=` while a job runs."""
        stream = self.stream
        if stream is None or stream.done or stream.job_id is None:
            return self._log
        return self._log.bind(job=stream.job_id)

    def _detected(self, fault: str, value: Any, text: str) -> None:
        self._events.append(Detected(fault, value, text))

    def _write_refused(self) -> MachineError:
        if self.halted:
            return FaultActive(
                f"{self.id}: internal fault, nothing is written until machine.reset", ["internal"]
            )
        return NotConnected(f"{self.id}: link lost")

    def _locked_message(self) -> str:
        state = self.model.state
        name = state.name if state is not None else "an unknown state"
        detail = self.model.last_exception_message()
        return f"{self.id} is in {name}" + (f": {detail}" if detail else "")


def _context_changed(machine: str, admitted: Context, now: Context) -> str:
    what = {
        Context.HOLD: "a hold began",
        Context.JOB: "an operation started",
        Context.FREE: "the hold ended",
    }[now]
    if admitted is Context.HOLD and now is not Context.HOLD:
        what = "the hold ended"
    return f"{machine}: {what} before the line was written; it was not sent"
