"""The modal-state model: G-code lines in, modal state out. No I/O, O(1) memory.

`GcodeModel.step(line)` reads one line of a file as the controller would, in
RS274/NGC's order of execution within a block, and keeps what it changes:
the modes, F S T, coolant, offsets and the position. `state()` is a snapshot;
`ModalState.preamble()` the G-code to restore it. Where controllers differ
the `Dialect` decides (dialects.py, docs/gcode.md).

What the file alone cannot tell is None in the snapshot and NaN inside: the
position before the first absolute move (unless a start is given), the G28/G30
home positions and the G54.. offsets (unless given, from the machine's
settings), the position after a probe (G38.x), a canned cycle, or a tool
length offset change (G43/G49: the offset is the machine's).

Not modelled, and warned about: parameters and expressions (`#1`, `[1+2]`),
O-word subroutines and loops, cutter compensation (G41/G42: the path is offset
from the programmed one), canned cycles (G81-G89), G10 L1/L10/L11 (tool table),
rotation (G10 R). The model then keeps going, as the controller would with
whatever it can read.

`GcodeModel` is one class written in layers, a file each. A layer calls only
itself and the layers below it, and none overrides another:

    model.py    GcodeModel  a line of text: comments, block delete, words, the
                            errors that stop the analysis (ProgramError)
    blocks.py   Blocks      one block's effect, group by group, in RS274/NGC's order
    motion.py   Motion      where a move ends: lines, arcs, probes, canned cycles
    figures.py  Figures     each move's extent and time, for the analysis
    modes.py    Modes       the state, declared once; warnings; the snapshot
"""

from __future__ import annotations

from collections.abc import Iterable

from hostd.protocol.gcodestate.blocks import Blocks
from hostd.protocol.gcodewords import (
    INTEGER_DIGITS,
    not_a_number,
    read_words,
    strip_comments,
    too_long,
)


class ProgramError(Exception):
    """A line no board may run as the file wrote it: the analysis stops and says where.

    `line` is the file's line number (1-based). Today: a number with more integer
    digits than a board reads (it wraps past 2**31; Python reads 400 nines as
    infinity, which a preamble would have sent as `Finf`), or one spelled `inf`/`nan`.
    """

    def __init__(self, line: int, message: str) -> None:
        super().__init__(line, message)  # both in args: it is pickled back from a worker
        self.line = line
        self.message = message

    def __str__(self) -> str:
        return f"line {self.line}: {self.message}"


class GcodeModel(Blocks):
    """Reads a G-code file line by line and keeps the controller's modal state.

    Its arguments are `Modes`'s (modes.py), which declares the state they set.
    """

    # --- reading -----------------------------------------------------------------

    def feed_lines(self, lines: Iterable[str]) -> GcodeModel:
        for text in lines:
            self.step(text)
        return self

    def step(self, text: str) -> None:
        """Read one line of the file (its number is the count of lines read)."""
        self.line += 1
        if "(" in text or ";" in text:
            text, unclosed = strip_comments(text)
            if unclosed:
                self.warn("an unclosed comment: the rest of the line is ignored")
        text = text.strip()
        if not text:
            return
        first = text[0]
        if first == "%":
            return
        if first == "/":
            if self.block_delete:
                return
            text = text[1:]
        text = text.upper()
        words, end = read_words(text)
        if end != len(text):
            self._unreadable(text, end)
            return
        wide = too_long(words, text)
        if wide is not None:
            letter, number = wide
            shown = number if len(number) <= 16 else f"{number[:12]}...({len(number)} characters)"
            raise ProgramError(
                self.line,
                f"the number of {letter}{shown} has more than {INTEGER_DIGITS} integer digits: "
                "no board reads it (they wrap past 2,147,483,647)",
            )
        self.blocks += 1
        self._block(words)

    def _unreadable(self, text: str, at: int) -> None:
        if not_a_number(text, at):
            raise ProgramError(
                self.line,
                f"{text[at : at + 8]!r}: a number spelled inf or nan, which no board reads",
            )
        if text[0] == "O":
            self.warn("O-word subroutines and loops are not modelled")
        elif "#" in text or "[" in text:
            self.warn("parameters and expressions are not modelled: the line is ignored")
        else:
            self.warn("an unreadable line is ignored")
