"""The per-line shortcuts (issue 30) write and book exactly what the general path does.

Each dialect encodes a job's line with a shortcut for the common case (a
plain line, numbered), and takes a job line's plain answer without parsing
it. Neither may change a byte written or a count booked: each is compared
here with the general path it skips, over ordinary lines, over every edge
the shortcut tests for, and over arbitrary text.
"""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hostd.protocol.commands import InvalidCommand, encode_line
from hostd.protocol.g2core import G2Session
from hostd.protocol.grbl import codec
from hostd.protocol.grbl.session import GrblSession
from hostd.protocol.linemode import InFlight, LineModeSender
from hostd.protocol.program import MAX_LINE_NUMBER, number_line, program_lines, strip_line

EDGES = [
    "G1 X1 Y2 F3000",
    "g1x1y2",
    "G1 X1 ",  # a trailing blank: grbl strips it
    "G1 X1\t",
    "G1 X1 (a comment)",
    "G1 X1 ; the rest",
    "N10 G1 X1",  # its own N word: replaced
    "n5G0X0",
    "$H",
    "$J=G91 X1 F100",
    "?",
    '{"sr":null}',
    "{sr:n}",
    "E5",  # not a word a board reads
    "G1 X1e5",
    "M3 S1000",
    "G1 X1 !",  # a realtime byte inside a line: refused on grbl
    "G1 X" + "9" * 600,  # too long for either board
    "G1 X" + "1" * 120,  # past grbl's buffer, within g2core's line
    "G1 X1\u00a0",  # a non-ASCII blank
    "H1",
    "%",
    "",
    "  G1 X1",
]
NUMBERS = [0, 1, 12, 99_999, MAX_LINE_NUMBER, MAX_LINE_NUMBER + 1, -1]


def _general_g2(text: str, number: int | None) -> bytes | str:
    try:
        return encode_line(text if number is None else number_line(text, number))
    except InvalidCommand as exc:
        return f"refused {exc.refusal}"


def _general_grbl(text: str, number: int | None, rx: int) -> bytes | str:
    try:
        line = text if number is None else number_line(text, number)
        return codec.encode(line, max_bytes=rx - 1)
    except InvalidCommand as exc:
        return f"refused {exc.refusal}"


def _shortcut(session: G2Session | GrblSession, text: str, number: int | None) -> bytes | str:
    try:
        return session.encode_job_line(text, number)
    except InvalidCommand as exc:
        return f"refused {exc.refusal}"


@pytest.mark.parametrize("number", [*NUMBERS, None])
@pytest.mark.parametrize("text", EDGES)
def test_a_job_line_is_encoded_as_the_general_path_encodes_it(
    text: str, number: int | None
) -> None:
    g2 = G2Session("m1")
    grbl = GrblSession("m1")
    assert _shortcut(g2, text, number) == _general_g2(text, number)
    assert _shortcut(grbl, text, number) == _general_grbl(text, number, grbl.rx_size)
    grbl.rx_size = 256  # a grblHAL's buffer, as its [OPT:] says
    assert _shortcut(grbl, text, number) == _general_grbl(text, number, 256)


@settings(max_examples=400, suppress_health_check=[HealthCheck.too_slow])
@given(
    text=st.text(
        alphabet=st.sampled_from("GMNXYZFSE $;()%!?{}\t.-+0123456789 \u00a0"), max_size=40
    ),
    number=st.integers(min_value=-2, max_value=MAX_LINE_NUMBER + 2),
)
def test_any_text_is_encoded_as_the_general_path_encodes_it(text: str, number: int) -> None:
    g2 = G2Session("m1")
    grbl = GrblSession("m1")
    assert _shortcut(g2, text, number) == _general_g2(text, number)
    assert _shortcut(grbl, text, number) == _general_grbl(text, number, grbl.rx_size)


@given(st.lists(st.text(alphabet=st.sampled_from("G1 X;(%)\t\u00a0"), max_size=12), max_size=8))
def test_program_lines_strips_each_line_as_strip_line_does(lines: list[str]) -> None:
    expected = [(n, strip_line(t)) for n, t in enumerate(lines, start=1) if strip_line(t)]
    assert list(program_lines(lines)) == expected


def test_a_plain_answer_takes_the_oldest_job_line_off_the_books_only_if_it_is_its() -> None:
    sender = LineModeSender(window=4)
    job = object()
    first = InFlight(b"N1 G1 X1\n", job, 1)
    second = InFlight(b"N2 G1 X22\n", job, 2)
    sender.sent(first)
    sender.sent(second)
    assert sender.pop_job_answer(second.count) is None  # the count fits the second only
    assert sender.data_in_flight == 2
    assert sender.pop_job_answer(first.count) is first
    assert sender.data_in_flight == 1
    query = InFlight(b'{"sr":null}\n', "client")
    sender.sent(query)
    assert sender.pop_job_answer(second.count) is None  # a control line waits: read in full
    sender.oldest_control()
    assert sender.pop_job_answer(second.count) is second
    client = InFlight(b"G0 X1\n", "client")  # a client's line is no job's: read in full
    sender.sent(client)
    assert sender.pop_job_answer(client.count) is None
    assert sender.data_in_flight == 1
