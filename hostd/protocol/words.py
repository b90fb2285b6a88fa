"""The words a session speaks for a job and an operator, in its controller's own terms.

`Words` is the part of every session that only makes text: how a job's line
is written (`encode_job_line`, `encode_job_block`), and the lines of a jog, a
homing, a zero, a tool change, a laser test, a setting's read and write, and
what their answers say (`settings_found`, `machine_limits`, `board_offsets`,
`probe_input`). It decides nothing and holds no state: the engine and the
operations (hostd/machine) ask for these lines and send them as any other,
under the session's admission and flow control.

A dialect gives its own in one class (`G2Words` in g2words.py, `GrblWords` in
grbl/words.py), placed before `SessionBase` in its session's bases. What is
here is the interface, and the answer of a dialect that has no such word: a
refusal (-32602) the client reads, never a line the board would misread.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from hostd.protocol.commands import MAX_LINE_BYTES, InvalidCommand, Refusal
from hostd.protocol.gcode import WCS_P, work_zero_line
from hostd.protocol.gcodestate.resume import Board
from hostd.protocol.limits import MachineLimits
from hostd.protocol.messages import JsonObject
from hostd.protocol.probing import ProbeInput


class Words:
    """What a dialect says for a job, an operator's request and a setting (the module's
    docstring); `SessionBase` is built on it."""

    id: str  # the machine's, for the refusals (SessionBase sets it)

    def numbers_lines(self) -> bool:
        """Whether a job's lines go out with their file line as their N word: the board
        reports the N of the block it runs (g2core's `line`, grbl's `Ln:`). A board that
        cannot report it is sent the lines as the file has them (`encode_job_line`)."""
        return True

    def encode_job_line(self, text: str, number: int | None = None) -> bytes:
        """A job's line as it is written to this board; `number` its file line, written as
        its N word when the board reports one (`numbers_lines`).

        The board reports the N word of the block it runs (g2core's `line`, grbl's
        `Ln:`): that is how the host knows which file line was executing (`line_executed`).
        """
        raise NotImplementedError

    def encode_job_block(self, numbers: Sequence[int], texts: Sequence[str]) -> list[bytes] | None:
        """Numbered job lines (their file lines, their texts), each as `encode_job_line`
        writes it, in one pass when every one is a plain line; None (each then goes
        through `encode_job_line`) when any is not, or the dialect has no such pass."""
        return None

    def jog_lines(self, axes: Mapping[str, float], feed: float) -> list[str]:
        """The lines of a jog by these distances at this feed."""
        raise NotImplementedError

    def tool_change_line(self, text: str, tool: int | None) -> str:
        """A job's `M6` line as it goes to this board once the host has handled the change
        (held for it, or ignores it): `tool` is the tool it changes to, if known.

        Never empty: the job's line counts stay those of the file.
        """
        raise NotImplementedError

    def tool_length_lines(self, tool: int, delta: float) -> list[str]:
        """The lines that make `delta` (mm, along Z) the length offset of `tool`, in force."""
        raise NotImplementedError

    # The board answers its homing line only once the cycle has ended (grbl's `$H`).
    # False: it answers as the cycle starts, and the cycle ends when the state
    # leaves HOMING (g2core's G28.2).
    homing_answered_at_end = False
    # A line that asks for a full status report and is answered once the report has come
    # (g2core's `{sr:n}`, grbl's `?`): None where the board has none, and `query_status`
    # asks for one with no answer to wait for.
    report_line: str | None = None

    def line_limit(self) -> int:
        """The longest job line, its LF included, the board takes (g2core: 511 and the LF)."""
        return MAX_LINE_BYTES + 1

    def position_scales(self) -> tuple[float, float]:
        """mm per unit of the machine position and of the work position the board
        reports now (the snapshot's `machine_position`, `work_position`)."""
        return 1.0, 1.0

    def known_travel(self) -> dict[str, tuple[float, float]]:
        """The machine's travel per axis (mm) the session already knows, without asking."""
        return {}

    def home_lines(self, axes: Sequence[str] | None) -> list[str]:
        """The lines that home these axes (None: all of them), in the board's words."""
        raise InvalidCommand(
            Refusal.UNREADABLE, f"{self.id}: this controller's dialect has no homing command"
        )

    def homing_failed(self, report: Mapping[str, Any]) -> bool:
        """An exception report says the homing cycle failed (where the answer does not)."""
        return False

    def zero_line(self, wcs: str | None, axes: Mapping[str, float]) -> str:
        """`G10 L20 P<active WCS>`: the current position reads as given, in that WCS.

        The active WCS must be known and one of G54-G59 (RS274/NGC); a dialect
        that can name "the active one" without knowing it says so (grbl's P0).
        """
        p = WCS_P.get(wcs or "")
        if p is None:
            raise InvalidCommand(
                Refusal.UNREADABLE,
                f"the active work coordinate system is {wcs or 'unknown'}: select G54-G59 first",
            )
        return work_zero_line(p, axes)

    def spindle_max_setting(self) -> str | None:
        """The setting that holds the S word of full power (a laser's 100 %), or None
        where the board has none a host can read."""
        return None

    def beam_on_line(self, speed: float) -> str:
        """The line that lets a laser burn at S `speed` in the feed moves after it
        (a frame at low power); the moves end with `M5`."""
        return f"M3 S{gcode_number(speed)}"

    def laser_test_reads(self) -> list[str]:
        """Lines to send and have answered before `laser_test_lines`, for what they need
        to know of the board (grbl: `$G`, its modal feed)."""
        return []

    def laser_test_lines(self, speed: float, seconds: float) -> list[str]:
        """The lines of a test-fire at S `speed` for `seconds`, standing still; the last
        one turns the beam off. They go to the board together, so that its own dwell
        bounds the burn even if the host is gone before the last is answered."""
        raise InvalidCommand(
            Refusal.UNREADABLE, f"{self.id}: this controller's dialect has no laser test-fire"
        )

    def status_text(self, code: int) -> str:
        """The board's own words for a non-zero answer `code`, from its dialect's table.

        The engine describes a refused line with this (error 1005's `msg`), so a
        code is never read in another firmware's table. Never raises: the code
        comes from the board, which may run a build newer than the table.
        """
        raise NotImplementedError

    def alarm_line(self) -> str:
        """The line that raises an alarm on the board (`machine.alarm`).

        InvalidCommand (-32602) where the dialect has no host-raised alarm, so
        the client hears so instead of a line the board would misread.
        """
        raise InvalidCommand(
            Refusal.UNREADABLE, f"{self.id}: this controller's dialect has no host-raised alarm"
        )

    def shutdown_line(self) -> str:
        """The line that raises a shutdown on the board (`machine.shutdown`); as `alarm_line`."""
        raise InvalidCommand(
            Refusal.UNREADABLE,
            f"{self.id}: this controller's dialect has no host-raised shutdown",
        )

    def settings_read(self, keys: list[str]) -> list[str]:
        """The query lines that read these settings."""
        raise NotImplementedError

    def settings_write(self, values: Mapping[str, bool | int | float | str]) -> list[str]:
        """The lines that set these settings (InvalidCommand for a value never to send)."""
        raise NotImplementedError

    def settings_found(self, keys: list[str], bodies: list[JsonObject]) -> dict[str, Any]:
        """The settings the answers' bodies hold, by the names they were asked by."""
        raise NotImplementedError

    def limit_settings(self) -> list[str]:
        """The settings that hold the machine's travel, speeds and accelerations."""
        raise NotImplementedError

    def machine_limits(self, found: Mapping[str, Any]) -> MachineLimits:
        """The limits those settings say (`settings_found`'s answer to `limit_settings`)."""
        raise NotImplementedError

    def offset_reads(self) -> list[str]:
        """The queries that read the board's stored offsets (G54..), its G92 and its S."""
        raise NotImplementedError

    def board_offsets(self, bodies: list[JsonObject]) -> Board:
        """What the answers to `offset_reads` say, in mm (a resume plans from it)."""
        raise NotImplementedError

    def probe_input_reads(self) -> list[str]:
        """The queries that say which input the probe is ([] where the reports show it)."""
        raise NotImplementedError

    def probe_input(self, bodies: list[JsonObject]) -> ProbeInput:
        """How the probe input is seen, from the answers to `probe_input_reads`.

        InvalidCommand where the board has no probe input a G38 could trip on.
        """
        raise NotImplementedError

    def work_zero_line(self, values: Mapping[str, float]) -> str:
        """`G10 L20 P<n>`: the current position reads `values` in the active WCS.

        InvalidCommand where the active WCS cannot be named to the board.
        """
        raise NotImplementedError


def gcode_number(value: float) -> str:
    """A number as G-code takes it: plain decimal, at most four places, no exponent."""
    text = f"{value:.4f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text
