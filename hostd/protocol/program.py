"""From a G-code program's text to the lines that go to the board.

Comments, blank lines and `%` tape marks are stripped before sending: a `%`
line gets no answer from the board (its window slot would leak) and a blank
one neither; comments only cost bytes. Each sendable line keeps its 1-based
line number in the file, for progress, `start_line` and error messages.

Works on any iterable of lines, so a file is streamed, never read whole.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator

# `( ... )` comments (not nested, as in RS274NGC) and `;` to the end of line.
_COMMENT = re.compile(r"\([^)]*\)?|;.*")


def strip_line(text: str) -> str:
    """The part of one program line that goes to the board ("" for none)."""
    if "(" in text or ";" in text:
        text = _COMMENT.sub("", text)
    text = text.strip()
    if text.startswith("%"):
        return ""
    return text


def program_lines(lines: Iterable[str], start_line: int = 1) -> Iterator[tuple[int, str]]:
    """(file line number, line to send) for every sendable line at or after `start_line`."""
    for number, text in enumerate(lines, start=1):
        if number < start_line:
            continue
        sendable = strip_line(text)
        if sendable:
            yield number, sendable
