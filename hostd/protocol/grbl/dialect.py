"""grbl's (1.1 and grblHAL) entry in the dialect registry (dialects.py), registered on import.

The rules are the session's (`GrblSession`, session.py) and the tables it
reads: error and alarm texts (codes.py, grblHAL errors.c and alarms.c), the
states of its reports (report.py), the G-code it lacks or reads differently
(gcodestate/dialects.py), its realtime bytes (codec.py) and its maintenance
commands (maintenance.py). It has one port: no `control_port`.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from hostd.protocol.commands import Realtime
from hostd.protocol.dialects import DialectOptions, DialectSpec, SessionSettings, Words, register
from hostd.protocol.gcodestate.dialects import GRBL
from hostd.protocol.grbl import codec
from hostd.protocol.grbl.codes import ALARMS, ERRORS
from hostd.protocol.grbl.report import STATES
from hostd.protocol.grbl.session import GrblSession
from hostd.protocol.maintenance import grbl_maintenance, grbl_powered


class GrblOptions(DialectOptions):
    """grbl's own keys in a machine's table (docs/operations.md)."""

    # Seconds without a byte from the board (with 3 `?` unanswered) before the link is
    # taken for dead; longer while the board writes EEPROM or homes.
    link_silence: Annotated[float, Field(gt=0, le=3600)] = 10.0
    # Seconds a homing cycle may keep the board silent; unset, the bound its travel and
    # homing feeds give ($24, $25, $27, $130..).
    homing_timeout: Annotated[float, Field(gt=0, le=3600)] | None = None
    # A startup block ($N0/$N1) that moves runs at every reset. False: after a cancel or
    # a failed job hostd holds the board instead of resetting it (only machine.reset,
    # asked by the operator, resets it). True: it resets as usual.
    startup_motion: bool = False


def session(config: SessionSettings) -> GrblSession:
    """A grbl machine's session (one port; its heartbeat re-asks an unanswered `?`)."""
    options = GrblOptions.of(config)
    return GrblSession(
        config.id,
        status_interval=config.status_interval,
        heartbeat=config.heartbeat,
        link_silence=options.link_silence,
        homing_timeout=options.homing_timeout,
        handshake_timeout=config.handshake_timeout,
        startup_motion=options.startup_motion,
    )


def encode_job_line(text: str, max_bytes: int) -> bytes:
    """A line as grbl takes it (codec.py), within its receive buffer less one."""
    return codec.encode(text, max_bytes=max_bytes)


GRBL_DIALECT = register(
    DialectSpec(
        name="grbl",
        session=session,
        words=Words(statuses=dict(ERRORS), alarms=dict(ALARMS), states=dict(STATES)),
        gcode=GRBL,
        encode_line=encode_job_line,
        maintenance=grbl_maintenance,
        powered=grbl_powered,
        realtime={
            Realtime.FEEDHOLD: codec.FEEDHOLD,
            Realtime.CYCLE_START: codec.CYCLE_START,
            Realtime.RESET: codec.RESET,
            Realtime.ENQUIRY: codec.STATUS,  # hostd's status enquiry is grbl's `?`
        },
        simulator="hostd.sim.factories:grbl",
        options=GrblOptions,
    )
)
