"""G2Session's holds: what a board that holds is given to run inside its hold.

A layer of `G2Session` (g2core.py). A board is in a hold when its `stat` says
so, or when only its `hold` does (a `!` at rest, 101.05+). A client's action
line arriving then is admitted into the hold (`Context.HOLD`): it goes at
once, past the window, on the control lane, G-code as `{"gc2":...}` where the
build runs G-code in a hold (from 101.02); a text (`$`) line is refused, since
the board would keep it until the hold ends. Out of a hold an action line
waits for the window; while a job or an operation runs it is refused (busy).
"""

from __future__ import annotations

from typing import Any

from hostd.protocol.classes import CommandClass
from hostd.protocol.commands import encode_in_hold, encode_line
from hostd.protocol.errors import Busy
from hostd.protocol.g2books import G2Books
from hostd.protocol.vocabulary import Context, Queued


class G2Holds(G2Books):
    """A board's holds, as a client's action line meets them (see `G2Session`)."""

    def _admit_action(self, text: str, cls: CommandClass, token: Any) -> None:
        """An action line: in a hold, run inside it at once; free, under the window; else busy."""
        context = self._context()
        if context is Context.JOB:
            pausing = self.stream is not None and self.stream.paused
            raise Busy(
                f"{self.id}: the job is still entering its hold; send again once it holds"
                if pausing
                else f"{self.id} is running {'a job' if self._job_running() else 'an operation'}"
            )
        if context is Context.FREE:
            self._outbox.append(Queued(encode_line(text), cls, token, context))
            return
        if text.startswith("$"):
            # A text line is data: the board would keep it until the hold ends.
            raise Busy(f"{self.id} is in a hold: send settings as JSON ({{key:value}})")
        if _is_gcode(text) and not self.build.in_hold_gcode:
            raise Busy(
                f"{self.id} is in a hold, and its firmware (build {self.build.fb:g}) runs no "
                "G-code inside one (no gc2 before 101.02): resume or cancel first"
            )
        encoded = encode_in_hold(text) if _is_gcode(text) else encode_line(text)
        self._lane.append(Queued(encoded, cls, token, context))

    def out_of_hold(self) -> bool:
        """Also not while `hold` shows a hold that `stat` does not (a `!` at rest, 101.05+)."""
        return super().out_of_hold() and not self.model.hold

    def _context(self) -> Context:
        """A board that holds is in a hold, whatever its stat says (a `!` at rest, 101.05+)."""
        state = self.model.state
        if self.model.hold and not (state and state.is_lockout):
            return Context.HOLD
        return super()._context()


def _is_gcode(text: str) -> bool:
    return not text.startswith(("{", "$", "?"))
