"""A toy third dialect, from this folder alone: the proof that a dialect is one folder.

Nothing in hostd names it. A test registers `TOY` (`hostd.protocol.dialects.
register`), configures a machine with `dialect = "toy"` and `data_port =
"sim"`, and the daemon builds its session, its simulated board and its config
keys from this entry (tests/daemon/test_toy_dialect.py).

The toy protocol, host to board: a line of G-code words (G0, G1, G4, X, Y, Z,
F, P, N), `ALARM` (the host raises alarm 1), `UNLOCK` (leaves an alarm); the
realtime bytes `?` (a report), `!` (hold), `~` (resume), 0x18 (reset). Board
to host: `ok` or `err N` for each line, in order, one line at a time;
`<STATE x y z n>` for each `?`; `alarm N`; `hello toy 1` after a reset.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Annotated

from pydantic import Field

from hostd.protocol.commands import Realtime
from hostd.protocol.dialects import DialectOptions, DialectSpec, SessionSettings, Words
from hostd.protocol.gcodestate.dialects import G2CORE
from tests.toydialect.session import ToySession, encode
from tests.toydialect.words import ALARMS, ERRORS, STATES


class ToyOptions(DialectOptions):
    """The toy's own key: how long its greeting may take (a config schema addition)."""

    greeting: Annotated[float, Field(gt=0, le=60)] = 5.0


def session(config: SessionSettings) -> ToySession:
    return ToySession(
        config.id,
        status_interval=config.status_interval,
        handshake_timeout=ToyOptions.of(config).greeting,
    )


def encode_line(text: str, max_bytes: int) -> bytes:
    return encode(text, max_bytes)


TOY = DialectSpec(
    name="toy",
    session=session,
    words=Words(statuses=dict(ERRORS), alarms=dict(ALARMS), states=dict(STATES)),
    # The toy reads G-code as g2core does (its moves are all it has).
    gcode=replace(G2CORE, name="toy"),
    encode_line=encode_line,
    realtime={
        Realtime.FEEDHOLD: b"!",
        Realtime.CYCLE_START: b"~",
        Realtime.RESET: b"\x18",
        Realtime.ENQUIRY: b"?",
    },
    simulator="tests.toydialect.board:simulator",
    options=ToyOptions,
)
