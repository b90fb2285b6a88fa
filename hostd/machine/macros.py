"""Macros: named G-code snippets from the config, with numeric parameters, run as jobs.

A macro's text is the config author's; only its `{name}` placeholders are the
client's, and each takes a number within the parameter's bounds, written by the
daemon in plain decimal (no exponent, no text): a value can never be a line
break, a comment, a `$` or `{` command or another word. Unknown, missing,
non-numeric or out-of-bounds values are refused (-32602) before anything is sent.

The lines that result are then admitted as a job's lines are (`admit_program`):
no line may be a maintenance command (guard.py: those only go through
`machine.maintenance`), and every line must pass the job check (jobcheck.py):
the dialect's own line rules and length, numbers a board reads, no code the
dialect lacks, no M6 without a tool-change policy. The frame (operations.py) is
admitted the same way. Then it runs as a `make` job with no file, through the
supervisor's admission like any job (1003 unless idle, 204/205/206 in a lockout,
1007 with a fault active).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Final

from hostd.machine.config import PLACEHOLDER, MacroConfig, MacroParam
from hostd.machine.guard import classify, line_limit, tool_change_policy
from hostd.machine.jobstore import Job
from hostd.machine.machine import Machine
from hostd.protocol.commands import InvalidCommand
from hostd.protocol.errors import MachineError
from hostd.protocol.jobcheck import check_program
from hostd.protocol.program import program_lines
from hostd.protocol.refusals import Refusal

MAX_LINES: Final = 1000  # a macro is a snippet; a program is a file


class NoSuchMacro(MachineError):
    """api.md's 1004 (not found), as a missing file or job."""

    code = 1004


class MacroRefused(MachineError):
    """The macro's lines would not pass a job's checks: 1008, as job.start's."""

    code = 1008


def listing(machine: Machine) -> list[dict[str, Any]]:
    """macro.list's entries for one machine."""
    return [
        {
            "name": m.name,
            "params": {k: p.model_dump() for k, p in m.params.items()},
            "text": m.text,
            "machine": machine.id,
        }
        for m in machine.config.macros
    ]


def find(machine: Machine, name: str) -> MacroConfig:
    for macro in machine.config.macros:
        if macro.name == name:
            return macro
    known = ", ".join(m.name for m in machine.config.macros) or "none"
    raise NoSuchMacro(f"{machine.id} has no macro {name!r} (it has: {known})")


def expand(macro: MacroConfig, given: Mapping[str, Any]) -> list[str]:
    """The macro's lines with its parameters in place; InvalidCommand for a bad value."""
    unknown = sorted(set(given) - set(macro.params))
    if unknown:
        raise InvalidCommand(
            Refusal.UNREADABLE,
            f"macro {macro.name!r} has no param {', '.join(unknown)}"
            f" (it takes: {', '.join(sorted(macro.params)) or 'none'})",
        )
    words: dict[str, str] = {}
    for name, param in macro.params.items():
        words[name] = _value(macro.name, name, param, given.get(name, param.default))
    text = PLACEHOLDER.sub(lambda m: words[m.group(1)], macro.text)
    # As a file's lines are sent: comments and blank lines dropped (program.py).
    lines = [line for _, line in program_lines(text.splitlines())]
    if not lines:
        raise InvalidCommand(Refusal.EMPTY, f"macro {macro.name!r} has no line to send")
    if len(lines) > MAX_LINES:
        raise InvalidCommand(Refusal.UNREADABLE, f"macro {macro.name!r} has over {MAX_LINES} lines")
    return lines


def _value(macro: str, name: str, param: MacroParam, value: Any) -> str:
    """One parameter's value as the daemon writes it: a bounded plain decimal number."""
    if value is None:
        raise InvalidCommand(Refusal.UNREADABLE, f"macro {macro!r} needs param {name!r}")
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise InvalidCommand(
            Refusal.BAD_NUMBER, f"macro {macro!r}: param {name!r} is a number, not {value!r}"
        )
    if param.integer and value != int(value):
        raise InvalidCommand(
            Refusal.BAD_NUMBER, f"macro {macro!r}: param {name!r} is a whole number"
        )
    if not param.min <= value <= param.max:
        raise InvalidCommand(
            Refusal.BAD_NUMBER,
            f"macro {macro!r}: param {name!r} is {param.min:g} to {param.max:g}, not {value:g}",
        )
    if param.integer:
        return str(int(value))
    text = f"{float(value):.4f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text


def admit_program(machine: Machine, lines: list[str], what: str) -> None:
    """Every line as a job's line would be judged, before any is sent (see the docstring)."""
    for number, line in enumerate(lines, start=1):
        found = classify(machine, line)
        if found is not None:
            raise MacroRefused(
                f"{what}, line {number}: {found.why}: maintenance commands go only through"
                " machine.maintenance",
                {"line": number, "maintenance": found.kind.value},
            )
    findings = check_program(
        enumerate(lines, start=1),
        dialect=machine.config.dialect,
        max_line_bytes=line_limit(machine),
        tool_change=tool_change_policy(machine),
    )
    if findings:
        raise MacroRefused(
            f"{what} cannot run on {machine.id}: {findings.summary()}",
            {"problems": [f.to_json() for f in findings.found], "problems_total": findings.total},
        )


async def run(machine: Machine, name: str, given: Mapping[str, Any]) -> Job:
    """Expand, admit and start the macro as a job (its row: a make job with no file)."""
    macro = find(machine, name)
    lines = expand(macro, given)
    admit_program(machine, lines, f"macro {name!r}")
    return await machine.start_program(lines)
