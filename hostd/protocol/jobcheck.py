"""What a program holds that the board will refuse or must not run (issue 24, part 4).

`job.start` and `hostd analyze` read a file with this before anything moves,
so that a job does not fail at its 20,000th line for something the host could
see at the first. Each finding names its file line:

- `unsendable`: a line the session would refuse to write, as its own encoder
  says (grbl: longer than the receive buffer, `rx` of `[OPT:]` or 128, less
  its LF; a `!`, `?` or `~`, which grbl takes as realtime; anything but
  printable ASCII. g2core: over 511 bytes, NUL, control characters; see
  commands.py), with the N word the job gives each line counted in;
- `maintenance`: a maintenance command (protocol/maintenance.py) in a job;
- `number`: a number no board reads (spelled inf or nan, or with more integer digits
  than a board accumulates: gcodewords.INTEGER_DIGITS);
- `tool-change`: `M6` on a machine without a tool-change policy (the config's
  `tool_change`; absent or "refuse", no policy), or, where the machine holds for
  the change ("pause", "probe"), an `M6` with no T word on its line or before it
  (the operator could not be told which tool);
- `unsupported`: a G or M code the dialect lacks (gcodestate/dialects.py).

Under "ignore" each `M6` is a note, not a finding (`Findings.notes`): the job
runs without it (stripped), and says so. Under "refuse" or no policy the finding
says which of the two refused it.

Lines are read once, each in linear time: words by a pattern whose two
classes do not overlap, so it never backtracks.
"""

from __future__ import annotations

import functools
import math
import re
from collections.abc import Iterable
from dataclasses import dataclass

from hostd.protocol.commands import InvalidCommand
from hostd.protocol.dialects import DialectSpec, lookup
from hostd.protocol.gcodewords import (
    INTEGER_DIGITS,
    may_misspell_a_number,
    not_a_number,
    read_words,
    strip_comments,
    too_long,
)
from hostd.protocol.program import number_line
from hostd.protocol.toolchange import has_m6, tool_words

MAX_FINDINGS = 50  # listed one by one; the rest are counted
# A G or M word: the letter, blanks, the number. Disjoint classes: no backtracking. Lines
# come without comments (program_lines), so no word is read out of one.
_CODE = re.compile(r"([GM])\s*([0-9.]+)")
_POLICIES = frozenset({"pause", "probe", "ignore"})  # running.md's tool_change, but "refuse"
_HOLDS = frozenset({"pause", "probe"})  # the job holds at an M6 and names the tool


@dataclass(frozen=True, slots=True)
class Finding:
    line: int
    kind: str  # unsendable, maintenance, number, tool-change, unsupported
    text: str

    def to_json(self) -> dict[str, object]:
        return {"line": self.line, "kind": self.kind, "text": self.text}


@dataclass(frozen=True, slots=True)
class Findings:
    found: tuple[Finding, ...]  # the first MAX_FINDINGS
    total: int
    notes: tuple[Finding, ...] = ()  # M6s the "ignore" policy strips (the first MAX_FINDINGS)
    notes_total: int = 0
    lines: int = 0  # the sendable lines read: a job's total, counted in the same pass

    def __bool__(self) -> bool:
        return self.total > 0

    def summary(self) -> str:
        shown = "; ".join(f"line {f.line}: {f.text}" for f in self.found[:5])
        more = self.total - min(len(self.found), 5)
        return shown + (f"; and {more} more" if more > 0 else "")


def check_program(
    lines: Iterable[tuple[int, str]],
    *,
    dialect: str | DialectSpec,
    max_line_bytes: int,
    tool_change: str | None = None,
    numbered: bool = True,
) -> Findings:
    """Read a program's sendable lines ((file line, text), as `program_lines` gives them).

    `dialect`: the registry's entry (dialects.py), or its name. `max_line_bytes`: the
    longest line, its LF included, the board takes (grbl: its receive buffer less one;
    g2core 511). `numbered`: job lines carry `N<line>`.
    """
    spec = lookup(dialect) if isinstance(dialect, str) else dialect
    policy = tool_change in _POLICIES
    found: list[Finding] = []
    total = 0
    notes: list[Finding] = []
    notes_total = 0
    tool: int | None = None  # the last T word read
    read = 0
    for number, text in lines:
        read += 1
        finding = _check_line(number, text, spec, max_line_bytes, tool_change, numbered)
        selected = tool_words(text)
        tool = selected[-1] if selected else tool
        if finding is None and policy and has_m6(text):
            if tool_change in _HOLDS:
                if tool is None:
                    finding = Finding(
                        number,
                        "tool-change",
                        "M6 (tool change) with no T word on its line or before it: "
                        "the tool to load is unknown",
                    )
            else:
                notes_total += 1
                if len(notes) < MAX_FINDINGS:
                    notes.append(
                        Finding(
                            number,
                            "tool-change-ignored",
                            f"M6 (tool change{_to(tool)}) is stripped from the job: "
                            f"tool_change = {tool_change!r} on this machine, so the tool "
                            "is not changed",
                        )
                    )
        if finding is not None:
            total += 1
            if len(found) < MAX_FINDINGS:
                found.append(finding)
    return Findings(tuple(found), total, tuple(notes), notes_total, read)


def _refused_m6(tool_change: str | None) -> str:
    """Why job.start refuses an M6: the machine says so, or says nothing."""
    if tool_change == "refuse":
        return "M6 (tool change) is refused on this machine (tool_change = 'refuse')"
    return (
        "M6 (tool change) with no tool-change policy for this machine "
        "(its tool_change: pause, probe, ignore or refuse)"
    )


def _to(tool: int | None) -> str:
    return "" if tool is None else f" to T{tool}"


def _check_line(
    number: int,
    text: str,
    spec: DialectSpec,
    max_line_bytes: int,
    tool_change: str | None,
    numbered: bool,
) -> Finding | None:
    try:
        spec.encode_line(number_line(text, number) if numbered else text, max_line_bytes)
    except InvalidCommand as exc:
        return Finding(number, "unsendable", exc.message)
    if text[:1] in ("$", "{"):
        # Not G-code: a `$` or JSON command, maybe maintenance.
        found = spec.maintenance(text, {}, False)
        return None if found is None else Finding(number, "maintenance", found.why)
    bad = _bad_number(text)
    if bad is not None:
        return Finding(number, "number", bad)
    for letter, digits in _CODE.findall(text.upper()):
        code = letter + _code(digits)
        if code == "M6":
            if tool_change not in _POLICIES:
                return Finding(number, "tool-change", _refused_m6(tool_change))
            continue
        if code in spec.gcode.unsupported:
            return Finding(number, "unsupported", f"{code} is not supported by {spec.name}")
    return None


def _bad_number(text: str) -> str | None:
    """A number no board reads (`Finf`, `X1e400` spelled as 400 digits), as the model says."""
    if not may_misspell_a_number(text):
        return None
    return _read_bad_number(text)


def _read_bad_number(text: str) -> str | None:
    """`_bad_number`, read word by word."""
    code = strip_comments(text, " ")[0].upper().strip()
    words, end = read_words(code)
    if end != len(code) and not_a_number(code, end):
        return f"{code[end : end + 8]!r}: a number spelled inf or nan, which no board reads"
    wide = too_long(words, code)
    if wide is not None:
        return f"{wide[0]}{wide[1][:12]}...: more than {INTEGER_DIGITS} integer digits"
    return None


@functools.lru_cache(maxsize=1024)  # a program names a few codes, thousands of times each
def _code(number: str) -> str:
    """`01` is 1, `38.20` is 38.2: the code as the tables name it."""
    if number.isdigit() and len(number) < 6:
        return str(int(number))
    try:
        value = float(number)
    except ValueError:
        return number
    return f"{value:g}" if math.isfinite(value) else number
