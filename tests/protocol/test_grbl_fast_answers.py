"""grbl's session: the fast path takes a job's `ok`s only, never another line's answer.

The engine hands a read's lines to `receive_plain` first, which takes each run
of `ok`s answering the job's oldest lines in one pass (issue 30), and gives the
rest to `receive`. An `ok` that answers anything else must be read in full: a
line of a tool change's operation, written while the job is held at its M6,
is answered to the operation that sent it, and the job counts no line the
board did not answer for it (`lines_acked` never runs ahead of the board).
"""

from __future__ import annotations

from hostd.protocol.grbl import codec
from hostd.protocol.messages import Response
from hostd.protocol.stream import Stream
from hostd.protocol.vocabulary import Lane
from tests.protocol.test_grbl_session import Grbl


def read(grbl: Grbl, *lines: str) -> list[tuple[Lane, bytes]]:
    """The lines of one read as the engine gives them (engine.py `_receive`): each run
    of plain job answers to `receive_plain`, the line it stops at to `receive`."""
    session = grbl.session
    data = [line.encode() for line in lines]
    index = 0
    while index < len(data):
        at = session.receive_plain(data, index)
        if at < len(data):
            session.receive(data[at])
        index = at + 1
    return grbl.pump()


def test_an_operation_line_answered_while_the_job_holds_at_a_tool_change_is_its_own() -> None:
    grbl = Grbl()
    grbl.connect()
    stream = Stream(job_id=1, encode=lambda text, _n: codec.encode(text))
    stream.feed(1, "G1 X1 F100")
    stream.feed(2, "M6 T2", hold=True)  # the tool change: the job holds before it
    stream.feed(3, "G1 X2")  # the file goes on: its input has not ended
    grbl.session.start_stream(stream)
    assert [line for _, line in grbl.pump()] == [b"G1 X1 F100\n"]
    read(grbl, "ok")
    assert stream.held == 2 and stream.acked == 1
    grbl.session.set_operation(True)  # the tool change's own moves
    token = object()
    grbl.session.send("G53 G0 Z0", token, operation=True)
    assert grbl.pump() == [(Lane.DATA, b"G53 G0 Z0\n")]
    read(grbl, "ok")
    settled = grbl.settled(token)
    assert settled is not None and isinstance(settled.outcome, Response)
    assert settled.outcome.ok
    assert stream.acked == 1 and stream.last_acked_line == 1
