"""How `hostd run` cuts a file into `file.upload` pieces (pure: no daemon)."""

from __future__ import annotations

import base64
import io

from hostd.cli.commands import upload_chunks


def reassemble(pieces: list[tuple[str, str]]) -> bytes:
    return b"".join(
        base64.b64decode(data) if encoding == "base64" else data.encode("utf-8")
        for data, encoding in pieces
    )


def test_text_goes_as_utf8_in_pieces_of_at_most_the_chunk_size() -> None:
    text = b"G1 X1 Y2 F300\n" * 100

    pieces = list(upload_chunks(io.BytesIO(text), size=64))

    assert {encoding for _, encoding in pieces} == {"utf-8"}
    assert all(len(data.encode()) <= 64 for data, _ in pieces)
    assert reassemble(pieces) == text


def test_a_multibyte_character_is_never_split_between_pieces() -> None:
    text = ("(é 测 🛠)\n" * 50).encode()

    for size in range(4, 12):
        pieces = list(upload_chunks(io.BytesIO(text), size=size))
        assert {encoding for _, encoding in pieces} == {"utf-8"}, size
        assert reassemble(pieces) == text, size


def test_bytes_that_are_not_utf8_go_as_base64() -> None:
    data = bytes(range(256)) * 3

    pieces = list(upload_chunks(io.BytesIO(data), size=100))

    assert "base64" in {encoding for _, encoding in pieces}
    assert reassemble(pieces) == data


def test_text_that_would_escape_past_the_line_limit_goes_as_base64() -> None:
    control = b"\x01" * (512 * 1024)  # valid UTF-8, but six bytes a character in JSON

    [(data, encoding)] = list(upload_chunks(io.BytesIO(control)))

    assert encoding == "base64"
    assert base64.b64decode(data) == control


def test_an_empty_file_is_one_empty_piece() -> None:
    assert list(upload_chunks(io.BytesIO(b""))) == [("", "utf-8")]
