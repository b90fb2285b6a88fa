"""The one G-code tokenizer: every reader of G-code in hostd splits lines with it.

Five readers share it: the checks of what is sent (`protocol/gcode.py`), the
program reader (`protocol/program.py`), the modal model
(`protocol/gcodestate/model.py`) and the two simulated boards
(`sim/gcode.py`, `sim/grbl/parser.py`). Each keeps its own rules on top
(which comments nest, what ends a line, what a stray character means); the
splitting into comments and words is done here, once.

Linear by construction, whatever the line: every pattern here is
deterministic. Each alternative starts with a character no other alternative
of the same choice starts with, and every repetition is possessive (`*+`,
`++`, `?+`) or, for a group, greedy inside an atomic group (`(?>(?:...)*)`:
Python 3.11.0-3.11.4, Debian 12's, match a possessive group wrongly;
tests/test_patterns.py), so the engine never gives a character back to try
another split.
Before this, the model's line pattern let `[0-9]+\\.?[0-9]*` split `111` three
ways; "X111" sixteen times and a `#` took 27 s to refuse, holding the GIL
(docs/gcode.md, "Reading G-code in linear time"). `tests/protocol/
test_gcodewords.py` counts the work on n and 8n characters to hold every
reader to it.

A word is a letter, optional spaces or tabs, then a number: an optional sign,
then digits with an optional point and digits after it, or a point and digits
(`X1`, `X-1.`, `Y.5`, `F 300`). No exponent, no spaces inside the number: no
controller reads `X1e3` or `X- 1` as one number.
"""

from __future__ import annotations

import re

# A word: (letter, number). Possessive throughout; the two forms of a number start
# with a digit and with a point, so at most one of them can go on.
WORD = re.compile(r"([A-Za-z])[ \t]*+([-+]?+(?:[0-9]++(?:\.[0-9]*+)?+|\.[0-9]++))")
# The longest run of words (spaces and tabs around them) from the start of a text. Atomic,
# not `*+`: an iteration can fail after its letter ("X1 Y"), which 3.11.2 gets wrong.
_WORDS = re.compile(
    r"(?>(?:[ \t]*+[A-Za-z][ \t]*+[-+]?+(?:[0-9]++(?:\.[0-9]*+)?+|\.[0-9]++))*)[ \t]*+"
)
# A parenthesised comment, flat: to the first `)`, or to the end of the line when there
# is none (the caller decides what an unclosed one means); or `;` and the rest of the line.
_FLAT_COMMENT = re.compile(r"\([^)]*+\)?+|;")
# A letter whose number is spelled as Python's float() would read it, but no board does.
_NOT_A_NUMBER = re.compile(r"[A-Za-z][ \t]*+[-+]?+(?:inf|nan)", re.IGNORECASE)
# Ten digits in a row: the only way a number can have more than nine integer digits.
_TEN_DIGITS = re.compile(r"[0-9]{10}")

# The most integer digits a number may have (leading zeros not counted): below
# 1,000,000,000, as `numbers.BOARD_LIMIT` says for every number that reaches a board.
INTEGER_DIGITS = 9


def read_words(code: str) -> tuple[list[tuple[str, str]], int]:
    """The words at the start of `code`, and how far they reach.

    The second value is `len(code)` when the whole text is words (with spaces and
    tabs between them); else it is the index of the first character that does not
    start a word: a letter there has no number after it, anything else is no word.
    Letters are as written; callers that upper-case the text get upper-case letters.
    """
    end = _WORDS.match(code).end()  # type: ignore[union-attr]  # `*+` always matches
    return WORD.findall(code, 0, end), end


def strip_comments(text: str, replace: str = " ") -> tuple[str, bool]:
    """`text` with its flat comments replaced by `replace`, and whether one is unclosed.

    Flat, as LinuxCNC, grbl and the board's checks read them: a comment runs from
    `(` to the first `)`, and `;` comments out the rest of the line. An unclosed
    `(` takes the rest of the line with it (the second value is then True).
    """
    if "(" not in text and ";" not in text:
        return text, False
    out: list[str] = []
    pos = 0
    unclosed = False
    for m in _FLAT_COMMENT.finditer(text):
        out.append(text[pos : m.start()])
        token = m.group()
        if token == ";":
            pos = len(text)
            break
        if token[-1] != ")":
            unclosed = True
            pos = len(text)
            break
        out.append(replace)
        pos = m.end()
    out.append(text[pos:])
    return "".join(out), unclosed


def not_a_number(code: str, at: int) -> bool:
    """Whether the word at `at` spells its number `inf` or `nan` (`Xinf`, `F -NaN`)."""
    return _NOT_A_NUMBER.match(code, at) is not None


def may_misspell_a_number(text: str) -> bool:
    """False when no word of `text` can be `not_a_number` or `too_long`, in any reading
    of it: it holds neither `inf` nor `nan` (any case) and no ten digits in a row. A
    comment's removal (replaced by a blank) joins no digits and spells no word, so this
    holds for the text with its comments stripped too. The job check asks it first of
    every line: most say False at a seventh of reading the words."""
    upper = text.upper()
    return "INF" in upper or "NAN" in upper or _TEN_DIGITS.search(text) is not None


def too_long(words: list[tuple[str, str]], code: str) -> tuple[str, str] | None:
    """The first word of `code` whose number has more integer digits than a board reads.

    A board accumulates the integer part in a 32-bit integer and wraps past
    2,147,483,647; Python reads 400 nines as infinity. Cheap on every line: only
    a line with ten digits in a row looks at its words one by one.
    """
    if _TEN_DIGITS.search(code) is None:
        return None
    for letter, number in words:
        whole = number.lstrip("+-").partition(".")[0].lstrip("0")
        if len(whole) > INTEGER_DIGITS:
            return letter, number
    return None
