"""g2core's entry in the dialect registry (dialects.py): one object, registered on import.

The rules are the session's (`G2Session`, g2core.py) and the tables it reads:
status texts (status.py, g2core's error.h), combined states (states.py, which
are g2core's `stat` codes), the G-code it reads differently (gcodestate/
dialects.py), its realtime bytes (commands.py) and its maintenance commands
(maintenance.py). g2core has no alarm numbers of its own: an alarm is a
status (error.h STAT_*), in `statuses`.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from hostd.protocol.commands import InvalidCommand, Realtime, Refusal, encode_line, encode_realtime
from hostd.protocol.dialects import DialectOptions, DialectSpec, SessionSettings, Words, register
from hostd.protocol.g2core import G2Session
from hostd.protocol.gcodestate.dialects import G2CORE
from hostd.protocol.maintenance import g2core_maintenance, g2core_powered
from hostd.protocol.states import MachineState
from hostd.protocol.status import MESSAGES


class G2Options(DialectOptions):
    """g2core's own keys in a machine's table."""

    # Lines in flight under line-mode flow control (running.md; g2core.md section 4).
    window: Annotated[int, Field(ge=1, le=32)] = 4


def session(config: SessionSettings) -> G2Session:
    """A g2core machine's session; two ports when the config names a control port."""
    options = G2Options.of(config)
    return G2Session(
        config.id,
        window=options.window,
        status_interval=config.status_interval,
        heartbeat=config.heartbeat,
        handshake_timeout=config.handshake_timeout,
        signal_keys=config.signals.keys(),
        dual=config.control_port is not None,
    )


def encode_job_line(text: str, max_bytes: int) -> bytes:
    """A line as g2core takes it (commands.py), within `max_bytes` with its LF."""
    encoded = encode_line(text)
    if len(encoded) > max_bytes:
        raise InvalidCommand(Refusal.TOO_LONG, f"longer than the board takes ({max_bytes} bytes)")
    return encoded


G2CORE_DIALECT = register(
    DialectSpec(
        name="g2core",
        session=session,
        words=Words(
            statuses={code: text for code, text in MESSAGES.items() if code != 0},
            states={int(state): state for state in MachineState},
        ),
        gcode=G2CORE,
        encode_line=encode_job_line,
        maintenance=g2core_maintenance,
        powered=g2core_powered,
        realtime={command: encode_realtime(command) for command in Realtime},
        simulator="hostd.sim.factories:g2core",
        options=G2Options,
        ports=2,
    )
)
