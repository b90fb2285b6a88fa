"""The Engine's requests: what its Machine asks of the board, and what it reads.

A layer of `Engine` (engine.py). Each request goes to the session and is
delivered at once (`_deliver`): a line answered by the board (`send`, with
one timer a request, `_answer`, `_expire`), the lines that raise an alarm or
a shutdown, realtime bytes and overrides, leaving a lockout (`clear`), a
reset and the wait for the board to come back, a job's start, pause, resume,
release and stop, and the Machine's operations (`set_operation`). Here too
the views the Machine reads (`out_of_hold`, `quiet`, `wait_for`).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

from hostd.machine.engine_delivery import EngineDelivery
from hostd.machine.engine_state import LinkState
from hostd.machine.stream import JobStream
from hostd.protocol.commands import Realtime
from hostd.protocol.errors import (
    ControllerError,
    ControllerTimeout,
    MachineError,
    NotConnected,
)
from hostd.protocol.messages import Response


class EngineRequests(EngineDelivery):
    """The Machine's requests and views (see `Engine`)."""

    # -- requests --------------------------------------------------------

    def _future(self) -> asyncio.Future[Response]:
        """A future for an answer. Its outcome counts as seen even if its asker is gone."""
        future: asyncio.Future[Response] = asyncio.get_running_loop().create_future()
        future.add_done_callback(_seen)
        return future

    async def send(self, line: str, timeout: float = 10.0, *, operation: bool = False) -> Response:
        """One line from a client, answered by the board (ControllerError for a non-zero status).

        `operation`: the line is the running operation's own (a settings batch, a
        jog's G90), not a client's; it fits while that operation runs.
        """
        future = self._future()
        self.session.send(line, future, operation=operation)
        self._deliver()
        return await self._answer(future, timeout)

    async def _answer(self, future: asyncio.Future[Response], timeout: float) -> Response:
        """The board's answer, or ControllerTimeout; a line not yet written then never is.

        One timer a request, not a timeout scope and a shield: a query flood
        makes thousands of these a second, and a feedhold waits behind them.
        """
        timer = asyncio.get_running_loop().call_later(timeout, self._expire, future, timeout)
        try:
            response = await future
        except asyncio.CancelledError:
            self.session.cancel(future)  # the asker is gone: its line, if still waiting, too
            raise
        finally:
            timer.cancel()
        if not response.ok:
            raise ControllerError(response.status, self.session.status_text(response.status))
        return response

    async def alarm(self) -> Response:
        """Raise an alarm on the board, in its dialect's words (InvalidCommand if it has none)."""
        return await self.send(self.session.alarm_line())

    async def shutdown(self) -> Response:
        """Raise a shutdown on the board, in its dialect's words (InvalidCommand if it has none)."""
        return await self.send(self.session.shutdown_line())

    def _expire(self, future: asyncio.Future[Response], timeout: float) -> None:
        if not future.done():
            self.session.cancel(future)
            future.set_exception(
                ControllerTimeout(f"no answer from {self.id} within {timeout:g} s")
            )

    def realtime(self, command: Realtime) -> None:
        """Write a realtime byte now (it never waits), if the state admits it."""
        if self.link is None or self.link_state is LinkState.DOWN:
            raise NotConnected(f"{self.id} is not connected")
        self.session.realtime(command)
        self._deliver()
        if self._write_failed:
            raise NotConnected(f"{self.id}: not connected")

    def override(
        self, feed: int | None = None, rapid: int | None = None, spindle: int | None = None
    ) -> None:
        """Feed, rapid and spindle overrides, in percent, written now (realtime)."""
        self.session.override(feed, rapid, spindle)
        self._deliver()

    def safety_door(self) -> None:
        """The safety door opened, as the host says (grbl's 0x84)."""
        self.session.safety_door()
        self._deliver()

    def query_status(self) -> None:
        """Ask the board for a full status report now."""
        self.session.query_status()
        self._deliver()

    async def clear(self, timeout: float = 5.0) -> None:
        """Leave ALARM or SHUTDOWN with `{clear:n}`; PANIC is refused; otherwise a no-op.

        The session writes the clear only once none of our data lines is unanswered.
        """
        future = self._future()
        if not self.session.clear(future):
            return
        state = self.model.state
        self._deliver()
        await self._answer(future, timeout)
        try:
            async with asyncio.timeout(timeout):
                await self.wait_for(lambda: not self.session.locked())
        except TimeoutError:
            name = state.name if state is not None else "its lockout"
            raise ControllerTimeout(f"{self.id} did not leave {name}") from None

    async def reset(self, timeout: float = 10.0) -> None:
        """0x18: the board restarts; return once it is ready again.

        A g2core board reboots (its USB device goes away: the engine reconnects);
        a grbl board resets in place and its session re-syncs on the same link.
        """
        if self.link is None:
            raise NotConnected(f"{self.id} is not connected")
        self._restart_deadline = time.monotonic() + timeout
        self._ready.clear()
        self.session.reset()
        self._deliver()
        try:
            async with asyncio.timeout(timeout):
                await self._ready.wait()
        except TimeoutError:
            raise ControllerTimeout(f"{self.id} did not come back after reset") from None

    def admit_action(self) -> None:
        """Rejected (204/205/206) if an action may not reach the board now."""
        self.session.admit_action()

    def set_operation(self, running: bool) -> None:
        """The machine started or ended an operation; waiting client actions are judged again.

        Given while the Machine hears an event, it runs once the events are handed out.
        """
        self._command(lambda: self.session.set_operation(running))

    def start_stream(self, stream: JobStream) -> None:
        """Stream a job: the session takes its position, and the file feeds it from now on."""
        self.session.start_stream(
            stream.start(self.session.encode_job_line, self.session.encode_job_block)
        )
        self._job = stream
        stream.fill()
        self._deliver()

    def pause_stream(self) -> None:
        """The job's pause: `!`, and none of its lines is written until `resume_stream`."""
        self.session.pause_stream()
        self._deliver()

    def resume_stream(self) -> None:
        """The job's resume: `~`, and its lines flow again."""
        self.session.resume_stream()
        self._deliver()

    def release_stream(self, tool: int | None = None) -> None:
        """Pass the job's hold point (a tool change answered, `tool` put in): its lines
        flow again."""
        self.session.release_stream(tool)
        self._deliver()

    def stop_stream(self, code: int, text: str) -> None:
        """Fail the running job and stop the board: feedhold, then flush (a fault's effect).

        Given while the Machine hears an event, it runs once the events are handed out.
        """
        self._command(lambda: self._stop_stream(code, text))

    def _stop_stream(self, code: int, text: str) -> None:
        self.session.stop_stream(code, text)

    def kill_job(self) -> None:
        """The dialect's job kill, as a cancel writes it, with no job of ours streaming:
        the board drops what it holds and stops its spindle (a board found running an
        interrupted operation's lines). Given while the Machine hears an event, it runs
        once the events are handed out."""
        self._command(self._kill_job)

    def _kill_job(self) -> None:
        try:
            self.session.realtime(Realtime.JOB_KILL)
        except MachineError as exc:  # run from the delivery loop: never out of it
            self._log.warning("job kill not written", reason=exc.message)

    def interrupt_stream(self, code: int, text: str) -> None:
        """End the running job interrupted, and kill it on the board (the daemon stops).
        The job's end is handed out even if the kill is refused (a lockout drained it)."""
        try:
            self.session.interrupt_stream(code, text)
        finally:
            self._deliver()

    # -- views -----------------------------------------------------------

    def out_of_hold(self) -> bool:
        """No hold on the board and no flush under way: a free line is written as it is."""
        return self.session.out_of_hold()

    def quiet(self) -> bool:
        """Nothing of the host's queued or unanswered, but for queries; no stop under way."""
        return self.session.quiet()

    async def wait_for(self, predicate: Callable[[], bool]) -> None:
        """Until the predicate holds, re-checked after every answer and report.

        NotConnected if the link goes down first.
        """
        while not predicate():
            if self.link_state is LinkState.DOWN:
                raise NotConnected(f"{self.id}: link lost")
            self._changed.clear()
            await self._changed.wait()


def _seen(future: asyncio.Future[Response]) -> None:
    if not future.cancelled():
        future.exception()
