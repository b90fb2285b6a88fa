"""Line-mode bookkeeping: the window, and answers matched to the right line."""

from __future__ import annotations

import pytest

from hostd.protocol.linemode import InFlight, LineModeSender, SenderError
from hostd.protocol.messages import Response


def answer(count: int, body: dict[str, object] | None = None, status: int = 0) -> Response:
    return Response(body or {}, status, count, b"")


def data(line: str, n: int | None = None) -> InFlight:
    return InFlight(line.encode() + b"\n", source="job", file_line=n)


def control(line: str) -> InFlight:
    return InFlight(line.encode() + b"\n", source="client")


def test_window_limits_lines_in_flight() -> None:
    sender = LineModeSender(window=2)
    sender.sent(data("G1 X1"))
    sender.sent(data("G1 X2"))
    assert not sender.has_room
    with pytest.raises(SenderError):
        sender.sent(data("G1 X3"))
    sender.answered(answer(6))
    assert sender.has_room


def test_answers_come_back_in_order_with_their_file_lines() -> None:
    sender = LineModeSender(window=4)
    for n in (3, 5, 6):
        sender.sent(data(f"G1 X{n}", n))
    assert [sender.answered(answer(6))[0].file_line for _ in range(3)] == [3, 5, 6]
    assert len(sender) == 0


def test_json_lines_have_a_bounded_lane_of_their_own() -> None:
    # The board reads `{`-lines on every pass, ahead of waiting G-code: a flood of
    # queries must not take the job's slots, and stays within its own lane.
    sender = LineModeSender(window=1, control_window=2)
    sender.sent(control('{"xvm":null}'))
    sender.sent(control('{"yvm":null}'))
    assert sender.has_room and not sender.control_room
    assert sender.room(b"G1 X1\n") and not sender.room(b'{"zvm":null}\n')
    with pytest.raises(SenderError, match="control lane of 2"):
        sender.sent(control('{"zvm":null}'))
    sender.sent(data("G1 X1"))
    assert not sender.has_room


def test_urgent_query_goes_past_a_full_window_and_still_takes_a_slot() -> None:
    sender = LineModeSender(window=2)
    sender.sent(data("G1 X1"))
    sender.sent(data("G1 X2"))
    sender.sent(control('{"sr":null}'), urgent=True)
    assert len(sender) == 3
    sender.answered(answer(13, {"sr": {"stat": 5}}))
    assert not sender.has_room  # two job lines still out


def test_control_answer_that_overtakes_waiting_data_lines_is_matched_by_count() -> None:
    # G-code waits for planner room; the query is run at once and answered first.
    sender = LineModeSender(window=8)
    sender.sent(data("G1 X10 Y10", 1))  # 10 bytes: answered with 11
    sender.sent(control('{"sr":null}'))  # 11 bytes + LF: answered with 13
    got = sender.answered(answer(13, {"sr": {"stat": 5}}))[0]
    assert got.line == b'{"sr":null}\n'
    assert sender.answered(answer(11, {"n": 0}))[0].file_line == 1


def test_equal_counts_are_told_apart_by_the_body() -> None:
    sender = LineModeSender(window=8)
    sender.sent(data("G1 X1 Y2 Z3 "))  # 12 bytes: answered with 13
    sender.sent(control('{"sr":null}'))  # 11 bytes and its LF: also 13
    assert sender.answered(answer(13, {"sr": {}}))[0].control
    assert not sender.answered(answer(13, {"n": 7}))[0].control


def test_flush_drops_the_data_lines_the_board_discarded() -> None:
    sender = LineModeSender(window=4)
    sender.sent(data("G1 X1", 1))
    sender.sent(data("G1 X2", 2))
    sender.sent(control('{"sr":null}'))
    lost = sender.dropped()
    assert [e.file_line for e in lost] == [1, 2]
    assert len(sender) == 1  # the query is still answered
    assert sender.has_room


def test_an_answer_with_nothing_waiting_is_an_error() -> None:
    with pytest.raises(SenderError):
        LineModeSender().answered(answer(1))


def test_window_below_one_is_refused() -> None:
    with pytest.raises(ValueError):
        LineModeSender(window=0)


def test_a_line_the_board_never_answered_is_given_up_not_matched_one_off() -> None:
    # `{"xvm":null}` (12 + LF: 14) got no answer; the next one's count says so.
    sender = LineModeSender(window=4)
    sender.sent(control('{"xvm":null}'))
    sender.sent(control('{"yvm":null}'))
    sender.sent(control('{"travel":null}'))  # 15 bytes: answered with 17
    entry, skipped = sender.answered(answer(17, {"travel": 1}))
    assert entry.line == b'{"travel":null}\n'
    assert [e.line for e in skipped] == [b'{"xvm":null}\n', b'{"yvm":null}\n']
    assert len(sender) == 0


def test_a_count_that_fits_no_line_goes_to_the_oldest() -> None:
    sender = LineModeSender(window=4)
    sender.sent(data("G1 X1", 1))
    entry, skipped = sender.answered(answer(99))
    assert (entry.file_line, skipped) == (1, [])


def test_an_answer_too_long_gives_up_the_control_line_being_run() -> None:
    # json_parser.cpp sends `er` 113 instead of the answer to the `{`-line it is on:
    # the oldest control line; data lines waiting for planner room are not it.
    sender = LineModeSender(window=4)
    sender.sent(data("G1 X1", 1))
    sender.sent(control('{"xvm":null}'))
    sender.sent(control('{"yvm":null}'))
    given_up = sender.oldest_control()
    assert given_up is not None and given_up.line == b'{"xvm":null}\n'
    assert sender.answered(answer(14, {"yvm": 1}))[0].line == b'{"yvm":null}\n'
    assert sender.answered(answer(6))[0].file_line == 1


def test_book_records_a_line_only_while_its_kind_has_room() -> None:
    sender = LineModeSender(window=1, control_window=1)
    assert sender.book(data("G1 X1", 1))
    assert not sender.book(data("G1 X2", 2))  # the window is full: nothing recorded
    assert sender.book(control('{"sr":n}'))  # its own lane still has room
    assert not sender.book(control('{"xvm":n}'))
    assert len(sender) == 2


def test_a_plain_answer_is_the_oldest_data_lines_only_when_nothing_else_can_take_it() -> None:
    sender = LineModeSender(window=4)
    sender.sent(data("G1 X1", 1))  # answered with 6
    sender.sent(data("G1 X22", 2))
    assert sender.pop_job_answer(7) is None  # fits the second, not the oldest
    sender.sent(control('{"sr":n}'))
    assert sender.pop_job_answer(6) is None  # a control line waits: read it in full
    assert sender.answered(answer(10, {"sr": {}}))[0].control
    assert len(sender) == 2  # nothing taken by the refusals
    oldest = sender.pop_job_answer(6)
    assert oldest is not None and oldest.file_line == 1
    assert len(sender) == 1  # taken off the books
    assert [sender.answered(answer(7))[0].file_line] == [2]
    sender.sent(data("G1 X1"))  # a client's data line, no file line: read in full
    assert sender.pop_job_answer(6) is None and len(sender) == 1


def test_a_run_of_job_answers_is_taken_in_any_plain_form_and_stops_at_the_first_other() -> None:
    """`pop_job_answers` compares jv 4's answer to a numbered line whole first; any
    other plain form of the answer (no `n`, below jv 4; an `n` it did not expect) is
    matched as before, by its status and count: the same lines taken either way."""
    sender = LineModeSender(window=4)
    for n, line in ((7, "N7 G1 X1"), (8, "N8 G1 X22"), (9, "N9 G1 X3"), (10, "N10 G1 X4")):
        sender.sent(InFlight(line.encode() + b"\n", source="job", file_line=n))
    answers = [
        b'{"r":{"n":7},"f":[1,0,9]}',  # jv 4, as compared whole
        b'{"r":{},"f":[1,0,10]}',  # no `n`
        b'{"r":{"n":99},"f":[1,0,9]}',  # an `n` of another line: the count decides
        b'{"r":{"n":10},"f":[1,0,11]}',  # a count that is not the line's: stop
    ]
    assert sender.pop_job_answers(answers, 0, "job") == (3, [7, 8, 9])
    assert len(sender) == 1  # the fourth is left for the full reading
    assert sender.pop_job_answers([b'{"r":{"n":10},"f":[1,0,11]}'], 0, "job") == (0, [])
    assert sender.pop_job_answers([b'{"r":{"n":10},"f":[1,0,10]}'], 0, "other") == (0, [])
    assert sender.pop_job_answers([b'{"r":{"n":10},"f":[1,1,10]}'], 0, "job") == (0, [])
    assert sender.pop_job_answers([b'{"r":{"n":10},"f":[1,0,10]}'], 0, "job") == (1, [10])
