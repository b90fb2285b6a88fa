"""Text-mode commands (`$xvm`, `$xvm=1`) read as the board's text parser reads them, or refused."""

from __future__ import annotations

import pytest

from hostd.protocol.classes import CommandClass, classify
from hostd.protocol.commands import InvalidCommand, Refusal, validate_line
from hostd.protocol.textmode import TextCommand, read_text_command


@pytest.mark.parametrize(
    ("line", "command"),
    [
        ("$xvm", TextCommand("xvm", None)),
        ("$XVM", TextCommand("xvm", None)),
        ("$xvm=16000", TextCommand("xvm", 16000)),
        ("$xvm:16000", TextCommand("xvm", 16000)),
        ("$xvm 16000", TextCommand("xvm", 16000)),  # the board's relaxed separators
        ("$xvm= 16000", TextCommand("xvm", 16000)),
        ("$1sa=1.8", TextCommand("1sa", 1.8)),
        ("$clear", TextCommand("clear", None)),
    ],
)
def test_text_commands_are_read_as_the_board_reads_them(line: str, command: TextCommand) -> None:
    assert read_text_command(line) == command


def test_a_space_separated_value_is_a_set_and_classified_as_an_action() -> None:
    # Before, only `=` made a SET: `$xvm 100` passed as a query, though the board sets it.
    assert classify("$xvm 100") is CommandClass.ACTION
    assert classify("$xvm") is CommandClass.QUERY
    assert classify("$clr") is CommandClass.CLEAR


@pytest.mark.parametrize(
    ("line", "why"),
    [
        ("$xvm = 100", Refusal.UNREADABLE),  # the board reads a GET: the value is "= 100"
        ("$xvm=", Refusal.UNREADABLE),
        ("$xvm=abc", Refusal.UNREADABLE),
        ("$xvm=1 2", Refusal.UNREADABLE),
        ("$xvm=0x10", Refusal.UNREADABLE),
        ("$xvm=inf", Refusal.UNREADABLE),
        ("$", Refusal.UNREADABLE),
        ("$abcdefghij", Refusal.UNREADABLE),  # the board cuts names at 9 characters
        ("?sr", Refusal.UNREADABLE),
        ("$xvm=1e300", Refusal.BAD_NUMBER),
        ("$xvm=1000000000", Refusal.BAD_NUMBER),
        ("H1", Refusal.HELP),  # any line starting with H prints the help screens
        ("help", Refusal.HELP),
        ("$help", Refusal.HELP),
        ("$defa", Refusal.HELP),
        ("$flash", Refusal.BOOTLOADER),
        ("$jv=0", Refusal.RESERVED_KEY),
        ("$ej 0", Refusal.RESERVED_KEY),
        ("$defa=1", Refusal.RESERVED_KEY),
    ],
)
def test_text_commands_the_host_cannot_be_sure_of_are_refused(line: str, why: Refusal) -> None:
    with pytest.raises(InvalidCommand) as err:
        validate_line(line)
    assert err.value.refusal is why
    assert err.value.message
