"""Splitting the board's byte stream into lines does not depend on how the bytes arrive."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from hostd.protocol.framing import LineBuffer
from tests.fuzz.strategies import fuzz

# Mostly line-ish bytes, with LF and CR common enough to matter.
streams = st.lists(
    st.sampled_from([b"\n", b"\r", b"\r\n", b"{", b"}", b"x", b"ok", b"\x00", b"\xff"])
    | st.binary(max_size=20),
    max_size=60,
).map(b"".join)
cuts = st.lists(st.integers(min_value=0), max_size=30)


def feed_in_chunks(stream: bytes, at: list[int], max_line: int) -> list[bytes]:
    buffer = LineBuffer(max_line)
    lines: list[bytes] = []
    start = 0
    for cut in [*sorted({c % (len(stream) + 1) for c in at}), len(stream)]:
        lines += buffer.feed(stream[start:cut])
        start = cut
    return lines


def reference(stream: bytes, max_line: int) -> list[bytes]:
    """What framing.py documents: split at LF, strip one CR; a line that grows past
    max_line is handed on once, cut at max_line (even before its LF arrives), and the
    rest of it up to the next LF is dropped."""
    *complete, rest = stream.split(b"\n")
    lines = []
    for line in complete:
        if len(line) > max_line:
            lines.append(line[:max_line])
        else:
            lines.append(line[:-1] if line.endswith(b"\r") else line)
    if len(rest) > max_line:
        lines.append(rest[:max_line])
    return lines


@fuzz(400)
@given(streams, cuts)
def test_any_chunking_gives_the_lines_of_the_whole_stream(stream: bytes, at: list[int]) -> None:
    max_line = 4096  # the default: these streams never reach it
    assert feed_in_chunks(stream, at, max_line) == reference(stream, max_line)


@fuzz(400)
@given(streams, st.integers(1, 16))
def test_byte_by_byte_no_line_is_longer_than_max_line(stream: bytes, max_line: int) -> None:
    lines = feed_in_chunks(stream, list(range(len(stream))), max_line)
    assert lines == reference(stream, max_line)
    assert all(len(line) <= max_line for line in lines)


@fuzz(400)
@given(streams, cuts, st.integers(1, 16))
def test_any_chunking_no_line_is_longer_than_max_line(
    stream: bytes, at: list[int], max_line: int
) -> None:
    # Found by this test: a whole over-long line (its LF included) read at once came out uncut.
    lines = feed_in_chunks(stream, at, max_line)
    assert all(len(line) <= max_line for line in lines)
    assert lines == reference(stream, max_line)
