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

from hostd.protocol.commands import MAX_LINE_BYTES, InvalidCommand, encode_line
from hostd.protocol.g2core import G2Session
from hostd.protocol.grbl import codec
from hostd.protocol.grbl.session import GrblSession
from hostd.protocol.linemode import InFlight, LineModeSender
from hostd.protocol.program import (
    BLOCK,
    MAX_LINE_NUMBER,
    number_line,
    program_lines,
    strip_line,
)

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
    # A classic build without USE_LINE_NUMBERS ([OPT:] without N): the line as it is.
    assert _shortcut(_unnumbered(), text, number) == _general_grbl(text, None, 128)


def _unnumbered() -> GrblSession:
    """A grbl session whose handshake read `[OPT:V,15,128]`: no N, so no `Ln:`."""
    grbl = GrblSession("m1")
    grbl.line_numbers = False
    assert not grbl.numbers_lines()
    return grbl


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
    assert _shortcut(_unnumbered(), text, number) == _general_grbl(text, None, grbl.rx_size)


@given(st.lists(st.text(alphabet=st.sampled_from("G1 X;(%)\t\u00a0"), max_size=12), max_size=8))
def test_program_lines_strips_each_line_as_strip_line_does(lines: list[str]) -> None:
    expected = [(n, strip_line(t)) for n, t in enumerate(lines, start=1) if strip_line(t)]
    assert list(program_lines(lines)) == expected


@settings(max_examples=60, suppress_health_check=[HealthCheck.too_slow])
@given(
    lines=st.lists(
        st.sampled_from(["G1 X1\n", "  G0 Y2  \n", "\n", "%\n", "G1 (c) X3\n", "; c\n"]),
        min_size=BLOCK - 5,
        max_size=2 * BLOCK + 5,
    ),
    start=st.integers(min_value=-1, max_value=2 * BLOCK + 6),
)
def test_program_lines_reads_blocks_as_it_would_read_each_line(
    lines: list[str], start: int
) -> None:
    """Read a block at a time (comments in some blocks only), from any start line."""
    expected = [
        (n, strip_line(t)) for n, t in enumerate(lines, start=1) if n >= start and strip_line(t)
    ]
    assert list(program_lines(lines, start)) == expected


PLAIN_MOVES = ["G1 X1 Y2 F3000", "g1x1y2", "M3 S1000", "G1 X-1.5 Y+2.", "S500 G1 X1"]
JOB_TEXTS = st.one_of(
    st.sampled_from(PLAIN_MOVES),
    st.sampled_from(EDGES),
    st.text(alphabet=st.sampled_from("GMNXYZFSE $;()%!?{}\t.-+0123456789 \u00a0"), max_size=20),
)


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(
    texts=st.lists(st.one_of(JOB_TEXTS.map(str.strip), JOB_TEXTS), min_size=1, max_size=12),
    first=st.one_of(st.integers(min_value=-2, max_value=20), st.just(MAX_LINE_NUMBER - 5)),
    rx=st.sampled_from([128, 256]),
)
def test_a_block_of_job_lines_is_encoded_as_each_line_is(
    texts: list[str], first: int, rx: int
) -> None:
    """A block in one pass, or None: never a byte other than each line's own encoding;
    and a block of plain moves is taken in one pass."""
    numbers = list(range(first, first + len(texts)))
    g2 = G2Session("m1")
    grbl = GrblSession("m1")
    grbl.rx_size = rx
    unnumbered = _unnumbered()
    unnumbered.rx_size = rx
    for session in (g2, grbl, unnumbered):
        block = session.encode_job_block(numbers, texts)
        each = [_shortcut(session, text, n) for n, text in zip(numbers, texts, strict=True)]
        if block is not None:
            assert block == each
        if all(t in PLAIN_MOVES for t in texts) and first >= 0 and numbers[-1] <= MAX_LINE_NUMBER:
            assert block is not None
    if all(t in PLAIN_MOVES for t in texts):  # unnumbered, whatever the numbers
        assert unnumbered.encode_job_block(numbers, texts) == [t.encode() + b"\n" for t in texts]


@pytest.mark.parametrize("extra", [-1, 0, 1])
def test_a_block_is_held_to_each_boards_line_length(extra: int) -> None:
    """Numbered lines at each board's longest, and one byte past it."""
    g2 = G2Session("m1")
    grbl = GrblSession("m1")
    for session, longest in ((g2, MAX_LINE_BYTES), (grbl, grbl.rx_size - 2)):
        # "N7 " and "G1", then "X1" words: a line of `longest + extra` bytes without its LF.
        size = longest + extra - len("N7 G1")
        text = "G1" + " X1" * (size // 3) + "1" * (size % 3)
        assert len(f"N7 {text}") == longest + extra
        block = session.encode_job_block([7], [text])
        assert block == ([_shortcut(session, text, 7)] if extra <= 0 else None)
    unnumbered = _unnumbered()
    text = "G1" + "X" * (unnumbered.rx_size - 4 + extra)  # with its LF, rx_size - 1 + extra
    block = unnumbered.encode_job_block([7], [text])
    assert block == ([_shortcut(unnumbered, text, 7)] if extra <= 0 else None)


def test_an_unnumbered_block_is_its_lines_and_no_more() -> None:
    """A text that holds a line end (never one of a file's) is not taken as two lines."""
    unnumbered = _unnumbered()
    assert unnumbered.encode_job_block([1, 2], ["G1 X1\nG1 X2", "G1 X3"]) is None
    assert unnumbered.encode_job_block([1], ["$H"]) is None  # `_pump` takes it line by line
    assert unnumbered.encode_job_block([1], ["{x:1}"]) is None
    assert unnumbered.encode_job_block([1, 2], ["G1 X1", "G10 L20 P1 X0"]) is None  # stores
    assert unnumbered.encode_job_block([1, 2], ["N5 G1 X1", "G1 X2"]) == [b"N5 G1 X1\n", b"G1 X2\n"]


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
