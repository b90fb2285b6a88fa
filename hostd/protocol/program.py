"""From a G-code program's text to the lines that go to the board.

Comments, blank lines and `%` tape marks are stripped before sending: a `%`
line gets no answer from the board (its window slot would leak) and a blank
one neither; comments only cost bytes. Each sendable line keeps its 1-based
line number in the file, for progress, `start_line` and error messages.

Works on any iterable of lines, so a file is streamed, never read whole.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator, Sequence
from itertools import chain, count, islice

from hostd.protocol.gcodewords import strip_comments

# A line's own N word (RS274/NGC: first on the line), replaced by the host's. Possessive:
# linear, as every G-code pattern (gcodewords.py).
_N_WORD = re.compile(r"[nN][ \t]*+[0-9]++[ \t]*+")
# The highest N that every dialect takes: grbl's MAX_LINE_NUMBER (gcode.h), 10,000,000;
# g2core's MAX_LINENUM is 2,000,000,000.
MAX_LINE_NUMBER = 10_000_000


def strip_line(text: str) -> str:
    """The part of one program line that goes to the board ("" for none)."""
    # `( ... )` comments (not nested, as in RS274NGC) and `;` to the end of line.
    if "(" in text or ";" in text:
        text, _ = strip_comments(text, "")
    text = text.strip()
    if text[:1] == "%":
        return ""
    return text


def program_lines(lines: Iterable[str], start_line: int = 1) -> Iterator[tuple[int, str]]:
    """(file line number, line to send) for every sendable line at or after `start_line`.

    Read BLOCK lines at a time, each block stripped in one pass (`strip_line` of
    each line): this runs for every line of every job, and once more to count
    them, so the iterator a job's stream takes its lines from is C's (`chain`,
    `islice`), not a generator resumed a line.
    """
    return chain.from_iterable(program_blocks(lines, start_line))


BLOCK = 256  # lines of the file read and stripped together


def program_blocks(lines: Iterable[str], start_line: int = 1) -> Iterator[list[tuple[int, str]]]:
    """`program_lines`, BLOCK lines of the file at a time: a list of their sendable
    lines (fewer where lines are blank or comments alone; empty if all are)."""
    lines = iter(lines)
    if start_line > 1:
        next(islice(lines, start_line - 1, start_line - 1), None)  # skip the lines before
    first = max(start_line, 1)
    # The file's lines themselves, numbered only as they are kept: no (number, line) a line
    # read, and the block's text joined whole (docs/performance.md, 2026-11-28 night).
    while block := list(islice(lines, BLOCK)):
        texts = "".join(block)
        numbered = zip(count(first), block, strict=False)  # a count never ends
        if "(" in texts or ";" in texts or "%" in texts:
            yield [(number, text) for number, line in numbered if (text := strip_line(line))]
        else:  # no comment and no tape mark in the block: each line only loses its blanks
            yield [(number, text) for number, line in numbered if (text := line.strip())]
        first += len(block)


# The leads `number_line` does not simply put `N<number> ` in front of: every other line
# (almost every job line) becomes f"N{number} {text}" when 0 <= number <= MAX_LINE_NUMBER.
# The dialects' `encode_job_line` test this first, to skip the general path. A set: one
# hash lookup a line, where a tuple compared the lead with each in turn.
NOT_PREFIXED = frozenset(("", "$", "{", "?", "n", "N"))


def numbered_block(numbers: Sequence[int], texts: Sequence[str]) -> str | None:
    """Lines as `number_line` numbers those whose lead it need not look at,
    f"N{number} {text}", each ending in LF, joined: what a dialect's
    `encode_job_block` matches whole against its plain-line pattern (which also
    refuses the leads `number_line` treats apart). None if a number is one that
    `number_line` leaves off."""
    if min(numbers) < 0 or max(numbers) > MAX_LINE_NUMBER:
        return None
    return "".join([f"N{number} {text}\n" for number, text in zip(numbers, texts, strict=True)])


def number_line(text: str, number: int) -> str:
    """A sendable line with `N<number>` in front, so the board reports which line it runs.

    The file's own N word is replaced (two on a line are an error). A line that is not
    G-code (`$`, `{`, `?`) and a number the board would refuse are left as they are: the
    board then reports the last number it read, which is behind, never ahead.
    """
    lead = text[:1]
    if lead in ("$", "{", "?") or not 0 <= number <= MAX_LINE_NUMBER:
        return text
    match = _N_WORD.match(text) if lead in ("n", "N") else None
    rest = text[match.end() :] if match else text
    return f"N{number} {rest}" if rest else f"N{number}"
