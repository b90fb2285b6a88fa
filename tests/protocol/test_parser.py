"""Every kind of line a board sends, including the real captures quoted in g2core.md."""

from __future__ import annotations

import pytest

from hostd.protocol.framing import LineBuffer
from hostd.protocol.messages import (
    Ack,
    Banner,
    ExceptionReport,
    Notice,
    QueueReport,
    Response,
    StatusReport,
    TextLine,
    Unparseable,
)
from hostd.protocol.parser import parse_line, plain_answer

BANNER_100_26 = (
    b'{"r":{"fv":0.99,"fb":100.26,"fbs":"100.26","fbc":"settings_test.h","hp":3,"hv":0,'
    b'"id":"0084-e739-18c6-294","msg":"SYSTEM READY"},"f":[1,0,1]}'
)
BANNER_89_03 = (
    b'{"r":{"fv":0.98,"fb":89.03,"hp":3,"hv":0,"id":"0213-2335-6343","msg":"SYSTEM READY"},'
    b'"f":[1,0,1]}'
)
BANNER_101_06 = (
    b'{"r":{"fv":0.99,"fb":101.06,"fbs":"101.06","fbc":"settings_default.h","hp":"g2v9",'
    b'"hv":"k","id":"1234-abcd","msg":"SYSTEM READY"},"f":[1,0,1]}'
)
BANNER_TINYG = (
    b'{"r":{"fv":0.97,"fb":440.21,"hp":1,"hv":8,"id":"9H3583","msg":"SYSTEM READY"},'
    b'"f":[1,0,1,6543]}'
)


@pytest.mark.parametrize(
    ("raw", "fb", "hp"),
    [(BANNER_100_26, 100.26, 3), (BANNER_89_03, 89.03, 3), (BANNER_101_06, 101.06, "g2v9")],
)
def test_g2core_banners_are_recognised_with_their_build(raw: bytes, fb: float, hp: object) -> None:
    msg = parse_line(raw)
    assert isinstance(msg, Banner)
    assert msg.fb == fb
    assert msg.hp == hp
    assert msg.id is not None
    assert not msg.is_tinyg


def test_tinyg_banner_is_flagged_for_refusal() -> None:
    msg = parse_line(BANNER_TINYG)
    assert isinstance(msg, Banner)
    assert msg.is_tinyg


def test_json_control_line_footer_counts_the_terminator() -> None:
    # `{"gc":"G1 X0"}\n` answered in g2#287.
    msg = parse_line(b'{"r":{"gc":"G1 X0"},"f":[1,0,16]}')
    assert isinstance(msg, Response)
    assert (msg.status, msg.count, msg.ok) == (0, 16, True)
    assert msg.body == {"gc": "G1 X0"}


def test_rejection_in_alarm_carries_status_204() -> None:
    msg = parse_line(b'{"r":{},"f":[1,204,26]}')
    assert isinstance(msg, Response)
    assert msg.status == 204
    assert not msg.ok


def test_clear_answer() -> None:
    msg = parse_line(b'{"r":{"clr":null},"f":[1,0,14]}')
    assert isinstance(msg, Response)
    assert msg.body == {"clr": None}


def test_jv4_response_carries_the_line_number() -> None:
    msg = parse_line(b'{"r":{"n":20},"f":[1,0,10]}')
    assert isinstance(msg, Response)
    assert msg.body["n"] == 20


def test_tinyg_four_element_footer_still_parses() -> None:
    msg = parse_line(b'{"r":{},"f":[1,0,10,4252]}')
    assert isinstance(msg, Response)
    assert (msg.status, msg.count) == (0, 10)


def test_footer_nested_in_body_as_some_tinyg_builds_send_it() -> None:
    msg = parse_line(b'{"r":{"xvm":16000,"f":[1,0,9]}}')
    assert isinstance(msg, Response)
    assert msg.status == 0


def test_requested_status_report_is_a_response_with_the_report() -> None:
    msg = parse_line(b'{"r":{"sr":{"stat":1,"posx":0.0}},"f":[1,0,8]}')
    assert isinstance(msg, Response)
    assert msg.status_report == {"stat": 1, "posx": 0.0}


def test_automatic_status_report() -> None:
    # g2#480
    msg = parse_line(b'{"sr":{"posx":3.25121,"vel":79.74,"stat":6,"hold":4}}')
    assert isinstance(msg, StatusReport)
    assert msg.fields["stat"] == 6
    assert msg.fields["posx"] == pytest.approx(3.25121)


def test_job_kill_exception_report() -> None:
    # The `er` 207 after ^D, g2#480.
    msg = parse_line(b'{"er":{"fb":101.03,"st":207,"msg":"Kill job - Job killed by ^d"}}')
    assert isinstance(msg, ExceptionReport)
    assert msg.status == 207
    assert msg.message.startswith("Kill job")
    assert msg.fields["fb"] == 101.03


def test_exception_report_without_status_keeps_what_it_has() -> None:
    msg = parse_line(b'{"er":{"msg":"odd"}}')
    assert isinstance(msg, ExceptionReport)
    assert msg.status is None
    assert msg.message == "odd"


@pytest.mark.parametrize(
    ("raw", "expected"),
    [(b'{"qr":48}', (48, None, None)), (b'{"qr":30,"qi":2,"qo":20}', (30, 2, 20))],
)
def test_queue_reports(raw: bytes, expected: tuple[int, int | None, int | None]) -> None:
    msg = parse_line(raw)
    assert isinstance(msg, QueueReport)
    assert (msg.qr, msg.qi, msg.qo) == expected


def test_requested_queue_report_is_a_response() -> None:
    assert isinstance(parse_line(b'{"r":{"qr":48},"f":[1,0,8]}'), Response)


def test_ack() -> None:
    assert isinstance(parse_line(b'{"ack":true}'), Ack)


def test_other_json_objects_are_notices() -> None:
    msg = parse_line(b'{"muted":true}')
    assert isinstance(msg, Notice)
    assert msg.fields == {"muted": True}


def test_text_mode_prompt_is_a_text_line() -> None:
    msg = parse_line(b"g2core[mm] ok> ")
    assert isinstance(msg, TextLine)
    assert msg.text == "g2core[mm] ok> "


@pytest.mark.parametrize(
    ("raw", "reason"),
    [
        (b'{"r":{},"f":[1,0', "malformed JSON"),
        (b"\xff\xfe garbage", "not valid UTF-8"),
        (b"ok\x00ok", "control characters"),
        (b'{"r":{}}', "footer"),
        (b'{"r":{},"f":[1,"x",3]}', "footer"),
        (b'{"r":[],"f":[1,0,3]}', "not an object"),
        (b'{"sr":5}', "not an object"),
        (b'{"er":"boom"}', "not an object"),
        (b'{"qr":"many"}', "non-integer"),
        (b"{" * 100_000, "malformed JSON"),
        (b'{"a":' + b"[" * 100_000 + b"]" * 100_000 + b"}", "malformed JSON"),
        (b'{"r":{"x":' + b"[" * 50_000 + b"]" * 50_000 + b'},"f":[1,0,1]}', "malformed JSON"),
    ],
)
def test_malformed_lines_become_unparseable_with_their_bytes(raw: bytes, reason: str) -> None:
    msg = parse_line(raw)
    assert isinstance(msg, Unparseable)
    assert reason in msg.reason
    assert msg.raw == raw


def test_no_byte_value_makes_the_parser_raise() -> None:
    for b in range(256):
        for raw in (bytes([b]), b"{" + bytes([b]) + b"}", b'{"r":{},"f":[1,0,' + bytes([b])):
            parse_line(raw)  # must not raise


def test_line_buffer_splits_across_chunks_and_strips_cr() -> None:
    buf = LineBuffer()
    assert buf.feed(b'{"r":{},"f"') == []
    assert buf.feed(b':[1,0,4]}\r\n{"ack":true}\nhal') == [b'{"r":{},"f":[1,0,4]}', b'{"ack":true}']
    assert buf.pending == 3
    assert buf.feed(b"f\n") == [b"half"]


def test_line_buffer_cuts_a_line_that_never_ends() -> None:
    buf = LineBuffer(max_line=10)
    out = buf.feed(b"x" * 25)
    assert out == [b"x" * 10]
    assert buf.feed(b"yyyy") == []  # still the same runaway line
    assert buf.feed(b"zz\nnext\n") == [b"next"]
    assert buf.pending == 0


def test_the_plain_answer_fast_path_agrees_with_the_json_parser() -> None:
    for raw in (
        b'{"r":{},"f":[1,0,4]}',
        b'{"r":{},"f":[1,204,26]}',
        b'{"r":{},"f":[1,0,1234]}',
        b'{"r":{"n":120},"f":[1,0,18]}',  # jv 4 echoes a numbered line's N word
        b'{"r":{"n":7},"f":[1,253,9]}',
    ):
        fast = parse_line(raw)
        slow = parse_line(raw.replace(b'{"r":{', b'{"r": {'))  # not the fast shape
        assert isinstance(fast, Response) and isinstance(slow, Response)
        assert (fast.body, fast.status, fast.count) == (slow.body, slow.status, slow.count)


def test_a_job_lines_answer_is_read_for_its_status_and_count_alone() -> None:
    def status_and_count(raw: bytes) -> tuple[bytes, bytes] | None:
        plain = plain_answer(raw)
        return None if plain is None else (plain[2], plain[3])

    assert status_and_count(b'{"r":{"n":120},"f":[1,0,18]}') == (b"0", b"18")
    assert status_and_count(b'{"r":{},"f":[1,0,5]}') == (b"0", b"5")
    assert status_and_count(b'{"r":{"n":120},"f":[1,20,18]}') == (b"20", b"18")  # not OK
    assert status_and_count(b'{"r":{"xvm":1},"f":[1,0,13]}') is None  # a body: read in full


# Forms real boards print that strict JSON refuses (issue 12, item 5). A float that
# is not a number is printed by the firmware's printf as `nan` / `inf`; 100.x builds
# print some strings bare (the fbs git-describe string).
FIRMWARE_FORMS = [
    (b'{"sr":{"posx":nan,"vel":inf,"feed":-inf,"stat":5}}', {"posx": None, "vel": None}),
    (b'{"sr":{"posx":-nan,"posy":INF}}', {"posx": None, "posy": None}),
    (b'{"sr":{"posx":NaN,"posy":-Infinity}}', {"posx": None, "posy": None}),
]


@pytest.mark.parametrize(("raw", "expected"), FIRMWARE_FORMS)
def test_nan_and_inf_are_read_as_unknown_values(raw: bytes, expected: dict[str, object]) -> None:
    msg = parse_line(raw)
    assert isinstance(msg, StatusReport)
    assert expected.items() <= msg.fields.items()


def test_an_unquoted_string_from_an_older_build_is_read_as_a_string() -> None:
    msg = parse_line(b'{"r":{"fbs":100.26-5-gabcd,"fb":100.26},"f":[1,0,10]}')
    assert isinstance(msg, Response)
    assert msg.body == {"fbs": "100.26-5-gabcd", "fb": 100.26}


@pytest.mark.parametrize(
    "raw",
    [b'{"r":{"a":}}', b"{xx yy}", b'{"r":{},"f":[1,0,4]x}', b'{"sr":{"posx":1}} junk"', b"{nan}"],
)
def test_what_is_really_unintelligible_stays_unparseable(raw: bytes) -> None:
    assert isinstance(parse_line(raw), Unparseable)
