"""What a command is, and whether it may reach a controller in ALARM, SHUTDOWN or PANIC.

Everything that decides "may this be written now?" lives here, in one
table. The first rule: nothing that moves the machine or changes its
settings reaches a locked-out controller, except what the controller itself
accepts to clear the lockout (g2core's alarm page; behaviour.md).

Two rows go beyond the table in behaviour.md, both decided for safety and
written down in docs/protocol.md:
- HALT (`!`, `%`, 0x04) only ever stops things, so it is always forwarded.
- `~` (cycle start) resumes motion, so it is an ACTION and refused.
"""

from __future__ import annotations

import re
from enum import Enum

from hostd.protocol.commands import Realtime
from hostd.protocol.relaxed import is_get, parse_relaxed
from hostd.protocol.states import MachineState
from hostd.protocol.status import Status
from hostd.protocol.textmode import parse_text_command


class CommandClass(Enum):
    QUERY = "query"
    CLEAR = "clear"
    PROGRAM_END = "program-end"
    RESET = "reset"
    HALT = "halt"
    ACTION = "action"


FORWARD = None
_ALARM = Status.COMMAND_REJECTED_BY_ALARM
_SHUTDOWN = Status.COMMAND_REJECTED_BY_SHUTDOWN
_PANIC = Status.COMMAND_REJECTED_BY_PANIC

# class -> (ALARM, SHUTDOWN, PANIC): None forwards, a status code refuses.
# In every other state everything is forwarded.
ADMISSION: dict[CommandClass, tuple[Status | None, Status | None, Status | None]] = {
    CommandClass.QUERY: (FORWARD, FORWARD, FORWARD),
    CommandClass.CLEAR: (FORWARD, FORWARD, _PANIC),
    CommandClass.PROGRAM_END: (FORWARD, _SHUTDOWN, _PANIC),
    CommandClass.RESET: (FORWARD, FORWARD, FORWARD),
    CommandClass.HALT: (FORWARD, FORWARD, FORWARD),
    CommandClass.ACTION: (_ALARM, _SHUTDOWN, _PANIC),
}
_COLUMN = {MachineState.ALARM: 0, MachineState.SHUTDOWN: 1, MachineState.PANIC: 2}

# Which admitted classes take the controller out of which lockout.
CLEARS: dict[CommandClass, frozenset[MachineState]] = {
    CommandClass.CLEAR: frozenset({MachineState.ALARM, MachineState.SHUTDOWN}),
    CommandClass.PROGRAM_END: frozenset({MachineState.ALARM}),
    CommandClass.RESET: frozenset({MachineState.ALARM, MachineState.SHUTDOWN, MachineState.PANIC}),
}

_REALTIME_CLASS = {
    Realtime.FEEDHOLD: CommandClass.HALT,
    Realtime.QUEUE_FLUSH: CommandClass.HALT,
    Realtime.JOB_KILL: CommandClass.HALT,
    Realtime.CYCLE_START: CommandClass.ACTION,
    Realtime.RESET: CommandClass.RESET,
    Realtime.ENQUIRY: CommandClass.QUERY,
}
_CLEAR_KEYS = frozenset({"clear", "clr"})
# Exactly M2 or M30, as g2core matches it: an N word or anything else defeats it.
_PROGRAM_END = re.compile(r"[mM](?:2|30)")


Table = dict[CommandClass, tuple[Status | None, Status | None, Status | None]]


def admit(
    command: CommandClass, state: MachineState | None, table: Table = ADMISSION
) -> Status | None:
    """None if the command may be written in this state, else the rejection status.

    `table` is a dialect's (g2core's by default; grbl's in grbl/books.py).
    """
    column = _COLUMN.get(state) if state is not None else None
    if column is None:
        return FORWARD
    return table[command][column]


def classify_realtime(command: Realtime) -> CommandClass:
    return _REALTIME_CLASS[command]


def classify(line: str) -> CommandClass:
    """The class of one (already validated) line, as the board will read it.

    Lines are classified only after `validate_line`, which refuses whatever
    the host cannot read exactly as the board does (commands.py): a duplicate
    name, JSON the board would misread, an ambiguous text command. Should an
    unvalidated line come here anyway, anything not recognised as harmless is
    an ACTION: unknown is unsafe.
    """
    text = line.strip()
    if text.startswith("{"):
        return _classify_json(text)
    if text == "?":
        return CommandClass.QUERY
    if text.startswith("$"):
        command = parse_text_command(text)
        if command is None or not command.is_get:
            return CommandClass.ACTION  # `$xvm=1` and `$xvm 1` alike: a SET
        return CommandClass.CLEAR if command.name in _CLEAR_KEYS else CommandClass.QUERY
    if _PROGRAM_END.fullmatch(text):
        return CommandClass.PROGRAM_END
    return CommandClass.ACTION


def _classify_json(text: str) -> CommandClass:
    obj = parse_relaxed(text)
    if not obj:
        return CommandClass.ACTION
    if not all(is_get(v) for v in obj.values()):
        return CommandClass.ACTION  # a SET, gc, gc2, or a SET-form clear
    if obj.keys() & _CLEAR_KEYS:
        return CommandClass.CLEAR
    # GETs; {alarm:n}, {shutd:n}, {panic:n} are GET-form too and only raise a lockout.
    return CommandClass.QUERY
