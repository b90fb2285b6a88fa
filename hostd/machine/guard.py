"""What `machine.send` refuses and `machine.maintenance` allows (issue 24, part 3).

The commands themselves are named in `hostd.protocol.maintenance`, per
dialect; this module is the policy, for one machine:
- `machine.send` refuses every maintenance command (-32602, `data.refusal`
  "maintenance", `data.maintenance` its kind), naming the way to do it on
  purpose;
- `machine.maintenance` sends one, and only one that is maintenance, only
  when the machine's config says `maintenance = true`, and never an absurd
  jog or g2core's bootloader and defaults (nothing on purpose needs them
  through the daemon);
- after a maintenance line the board took, what the daemon knows of the
  board's startup blocks is read again (`$N`), since the reset guard of the
  grbl session decides by them.
"""

from __future__ import annotations

import contextlib

import structlog

from hostd.machine.machine import Machine
from hostd.machine.rest import at_rest
from hostd.protocol.commands import InvalidCommand, Refusal
from hostd.protocol.errors import ControllerError
from hostd.protocol.maintenance import Kind, Maintenance, absurd_jog
from hostd.protocol.messages import Response

log = structlog.get_logger(__name__)


class MaintenanceRefused(InvalidCommand):
    """A maintenance command where it may not go: the caller's input (-32602)."""

    def __init__(self, found: Maintenance, message: str) -> None:
        super().__init__(Refusal.MAINTENANCE, message)
        self.found = found

    @property
    def data(self) -> dict[str, str]:
        return {"refusal": self.refusal.value, "maintenance": self.found.kind.value}


def _travel(machine: Machine) -> dict[str, tuple[float, float]]:
    """The travel the session already knows (grbl's `$130`.. from the handshake's `$$`)."""
    return machine.engine.session.known_travel()


def classify(machine: Machine, line: str) -> Maintenance | None:
    """The maintenance command `line` is on `machine`'s board, or None (its dialect's table)."""
    inches = machine.engine.model.units == "in"
    return machine.config.spec.maintenance(line, _travel(machine), inches)


def check_send(machine: Machine, line: str) -> None:
    """Refuse a maintenance command on `machine.send` (MaintenanceRefused), before anything."""
    found = classify(machine, line)
    if found is None:
        return
    how = (
        "it is never sent"
        if not found.on_purpose
        else "send it with machine.maintenance"
        + ("" if machine.config.maintenance else f" (set maintenance = true for {machine.id})")
    )
    raise MaintenanceRefused(found, f"{found.why}: machine.send refuses it; {how}")


def check_jog(machine: Machine, axes: dict[str, float]) -> None:
    """Refuse a `machine.jog` no machine's travel has room for, on either dialect.

    The distances are relative, in the machine's units: longer than the axis's travel
    span where the session knows it (grbl's `$130`..), else than SANE_JOG_MM.
    """
    words = "G91" + "".join(f"{axis.upper()}{distance:.6f}" for axis, distance in axes.items())
    why = absurd_jog(words, _travel(machine), inches=machine.engine.model.units == "in")
    if why is not None:
        found = Maintenance(Kind.ABSURD_JOG, why, on_purpose=False)
        raise MaintenanceRefused(found, f"{why}: machine.jog refuses it")


async def send_maintenance(machine: Machine, line: str, timeout: float) -> Response:
    """Send one maintenance command on purpose, where the machine's config allows it."""
    found = classify(machine, line)
    if found is None:
        raise InvalidCommand(
            Refusal.UNREADABLE, "not a maintenance command: send it with machine.send"
        )
    if not found.on_purpose:
        raise MaintenanceRefused(found, f"{found.why}: it is never sent")
    if not machine.config.maintenance:
        raise MaintenanceRefused(
            found,
            f"{found.why}: maintenance commands are off for {machine.id} "
            "(set maintenance = true in its [[machines]] table)",
        )
    machine.refuse_line_if_faulted(line)  # a startup block that acts runs as it is stored
    log.warning("maintenance command", machine=machine.id, line=line, kind=found.kind.value)
    response = await machine.engine.send(line, timeout=timeout)
    if found.kind is Kind.STARTUP_BLOCK:
        # The reset guard reads them anew. grbl runs a block once as it stores it, and
        # answers `$N` only at rest (gnea/grbl system.c:237; grblHAL system.c:726).
        with contextlib.suppress(ControllerError):  # ended in a lockout: read there too
            await at_rest(machine, timeout=timeout, what="the stored startup block")
        await machine.engine.send("$N", timeout=timeout)
    return response


def line_limit(machine: Machine) -> int:
    """The longest job line, its LF included, the board takes as its session knows it:
    grbl's receive buffer less one (`[OPT:]` or 128), g2core's 511 bytes and the LF."""
    return machine.engine.session.line_limit()


def numbers_lines(machine: Machine) -> bool:
    """Whether the machine's job lines go out numbered (`N<file line>`), as its session
    knows the board: not on a classic grbl built without line numbers."""
    return machine.engine.session.numbers_lines()


def tool_change_policy(machine: Machine) -> str | None:
    """running.md's `tool_change`; absent is no policy (an M6 is refused, as "refuse")."""
    return machine.config.tool_change
