"""Waiting until the board has run what the host gave it: one rule for the operator's
operations (operations.py), probing (probing.py) and a job's tool change (toolchange.py).

A board answers a move as it queues it, not as it ends it, and may report rest
before its planner starts the move. So "at rest" is three things at once:

- a status report read after the wait began (`model.reports` moved on from
  the count taken before the report was asked for): not one the board sent before
  the last line reached it;
- that report says the board rests (`is_resting`) and `there` holds (a position
  the moves were to reach), or that it is locked out (then ControllerError: the
  moves ended in the lockout, not where they were going);
- the host's side is settled: none of its lines unanswered and no stop under way.
  Outside a job that is `Engine.quiet()`: nothing queued or unanswered but
  queries, no job streaming, no stop under way. Inside a job held at a tool
  change (`in_job`) the job's stream is open, held at its `M6` and handing out
  nothing, so `quiet()` can never hold there: the rule is then every line written
  answered (`no_data_in_flight`) and no stop under way (`flushing`: a cancel's
  flush must not pass for a board that ran the measuring moves).

Where the board's own reports may be a status interval apart, `poll` asks again
at that period while the condition does not hold (probing: a report taken as the
move starts says it runs).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import TYPE_CHECKING

from hostd.protocol.errors import ControllerError, ControllerTimeout

if TYPE_CHECKING:
    from hostd.machine.machine import Machine


def settled(machine: Machine, *, in_job: bool = False) -> bool:
    """The host's side of "at rest" (the module's docstring says why two forms)."""
    engine = machine.engine
    if in_job:
        return engine.session.no_data_in_flight() and not engine.session.flushing()
    return engine.quiet()


async def at_rest(
    machine: Machine,
    there: Callable[[], bool] = lambda: True,
    *,
    timeout: float,
    what: str = "the move",
    in_job: bool = False,
    poll: float | None = None,
) -> None:
    """Until a report asked for now says the board rests (and `there` holds) with the
    host's side settled, or that it is locked out.

    ControllerTimeout ("`what` did not end") after `timeout` s; ControllerError
    ("`what` ended in ALARM") when a lockout ended it; NotConnected if the link goes.
    """
    engine = machine.engine
    model = engine.model
    asked = model.reports

    def done() -> bool:
        state = model.state
        return (
            model.reports > asked
            and state is not None
            and ((state.is_resting and there()) or state.is_lockout)
            and settled(machine, in_job=in_job)
        )

    try:
        async with asyncio.timeout(timeout):
            engine.query_status()
            if poll is None:
                await engine.wait_for(done)
            else:
                await _polling(machine, done, poll)
    except TimeoutError:
        raise ControllerTimeout(f"{machine.id}: {what} did not end") from None
    if model.state is not None and model.state.is_lockout:
        raise ControllerError(0, f"{machine.id}: {what} ended in {model.state.name}")


async def _polling(machine: Machine, done: Callable[[], bool], poll: float) -> None:
    """`wait_for(done)`, asking for a report again each `poll` s while it does not hold."""
    engine = machine.engine
    while True:
        try:
            async with asyncio.timeout(poll):
                await engine.wait_for(done)
            return
        except TimeoutError:
            engine.query_status()  # not yet: the board's next report may be far
