"""g2core's answers to a job's lines: each matched to its line, and what a bad one does.

Each test pins one rule of g2core.py's reading (docs/protocol.md): an error
answer in the board's compact form fails the job and kills what follows it,
as any other error answer does (the per-line shortcut takes only an OK); a
job line the board never answered fails the job, and the lines written
behind it are killed; and the lines a lockout refuses count as rejected, not
discarded (only the ALARM of hostd's own pre-101.02 kill discards them).
"""

from __future__ import annotations

import pytest

from hostd.protocol.states import MachineState as S
from hostd.protocol.stream import Stream
from hostd.protocol.vocabulary import Lane, StreamEnd
from tests.protocol.g2wire import BUILDS, Wire

KILL = b"\x04\n"
LIMIT = '{"er":{"fb":%s,"st":203,"msg":"Limit hit - input 1"}}'


def streaming(fb: float, texts: list[str]) -> tuple[Wire, Stream]:
    wire = Wire(fb)
    wire.connect()
    stream = Stream(job_id=1).feed_all(enumerate(texts, start=1))
    wire.session.start_stream(stream)
    wire.pump()
    return wire, stream


def compact(line: bytes, status: int) -> bytes:
    """A data line's answer as the board prints it: no blanks (the per-line shortcut's form)."""
    return b'{"r":{},"f":[1,%d,%d]}' % (status, len(line))


@pytest.mark.parametrize("fb", BUILDS)
def test_a_compact_error_answer_to_a_job_line_fails_the_job_and_kills(fb: float) -> None:
    wire, stream = streaming(fb, [f"G1 X{i} F1000" for i in range(1, 9)])
    first = wire.unanswered[0]
    wire.feed(compact(first, 108))  # STAT_BAD_NUMBER_FORMAT
    assert stream.acked == 0 and stream.rejected == 1
    assert stream.result is not None and stream.result.end is StreamEnd.FAILED
    assert (Lane.REALTIME, KILL) in wire.written


@pytest.mark.parametrize("fb", BUILDS)
def test_a_job_line_the_board_never_answered_fails_the_job_and_kills(fb: float) -> None:
    """An answer whose count fits a later line, not the oldest: the oldest got none (an
    answer too large for the board's buffer can vanish). Whether it ran is unknown, so
    the job fails and the lines behind it must not run."""
    wire, stream = streaming(fb, ["G1 X1 F1000", "G1 X22 F1000", "G1 X333 F1000"])
    second = wire.unanswered[1]
    wire.unanswered.remove(wire.unanswered[0])
    wire.answer(second, {})
    assert stream.result is not None and stream.result.end is StreamEnd.FAILED
    assert "no answer" in (stream.result.message or "")
    assert (Lane.REALTIME, KILL) in wire.written


@pytest.mark.parametrize("fb", [101.06, 100.26])
def test_lines_a_board_in_alarm_refuses_are_rejected_not_discarded(fb: float) -> None:
    """A board in ALARM reads the lines it held and answers each 204: the job counts them
    rejected. Discarded is for lines a flush or kill threw away, and (before 101.02) the
    lines hostd's own ^D caught, none here."""
    wire, stream = streaming(fb, [f"G1 X{i} F1000" for i in range(1, 9)])
    held = [x for x in wire.unanswered if not x.startswith(b"{")]
    wire.feed(LIMIT % fb)
    assert stream.result is not None and stream.result.end is StreamEnd.FAILED
    for line in held:
        wire.answer(line, {}, status=204)
    wire.report(stat=2)
    assert wire.session.model.state is S.ALARM
    assert stream.rejected == len(held) and stream.discarded == 0
    assert stream.acked + stream.rejected + stream.discarded == stream.sent


@pytest.mark.parametrize("fb", BUILDS)
def test_a_homing_failure_reported_apart_mid_job_fails_the_job_and_kills(fb: float) -> None:
    """cycle_homing.cpp answers the G28.2 with OK and reports its failure in an `{r}` of
    its own (count 1, answering no line). The moves written behind the G28.2 would run
    from a position nobody knows: the job fails and they are killed."""
    wire, stream = streaming(fb, ["G28.2 X0", "G1 X10 F1000", "G1 X20 F1000"])
    wire.answer(b"G28.2 X0\n", {})
    wire.feed('{"r":{"msg":"Homing error - Switches misconfigured"},"f":[1,240,1]}')
    assert stream.result is not None and stream.result.end is StreamEnd.FAILED
    assert (Lane.REALTIME, KILL) in wire.written
