"""A g2core session driven by plain calls: the lines a board prints in, the bytes it writes out.

`Wire` keeps everything the session wrote and every event it gave, and
answers lines the way g2core does: an `{r}` whose footer count is the
line's length as the board counts it (a data line of L bytes is answered
with L + 1, a control line with L + 2). No ports and no clock but the one
the test moves.
"""

from __future__ import annotations

import json
from typing import Any

from hostd.protocol.g2core import G2Session
from hostd.protocol.vocabulary import Event, Lane, Settled

BANNER = (
    '{"r":{"fv":1.0,"fb":101.06,"hp":3,"hv":0,"id":"3X3566-YMB","msg":"SYSTEM READY"},"f":[1,0,1]}'
)
BUILDS = (100.26, 101.03, 101.06)  # one of each set of rules (hostd/protocol/g2builds.py)
JOB_KILLERS = tuple(fb for fb in BUILDS if fb >= 101.02)  # ^D kills with a flush; gc2


def banner(fb: float) -> str:
    return BANNER.replace('"fb":101.06', f'"fb":{fb}')


REPORT = {"stat": 1, "posx": 0, "posy": 0, "posz": 0, "unit": 1}


class Wire:
    def __init__(self, fb: float = 101.06, **options: Any) -> None:
        self.fb = fb
        self.now = 0.0
        self.session = G2Session("m1", clock=lambda: self.now, **options)
        self.written: list[tuple[Lane, bytes]] = []
        self.events: list[Event] = []
        self.unanswered: list[bytes] = []  # written lines the test has not answered yet

    # -- moving the session --------------------------------------------------

    def pump(self) -> list[tuple[Lane, bytes]]:
        out = self.session.data_to_send()
        self.written += out
        # Realtime bytes get no answer, on the realtime lane or (two ports) the data lane.
        self.unanswered += [
            data for lane, data in out if lane is not Lane.REALTIME and not _single(data)
        ]
        self.events += self.session.events()
        return out

    def feed(self, *lines: str | bytes) -> list[tuple[Lane, bytes]]:
        for line in lines:
            self.session.receive(line.encode() if isinstance(line, str) else line)
        return self.pump()

    def at(self, now: float) -> list[tuple[Lane, bytes]]:
        self.now = now
        self.session.tick()
        return self.pump()

    def answer(self, line: bytes, body: dict[str, Any] | None = None, status: int = 0) -> None:
        """The board's answer to one written line (it must be unanswered)."""
        self.unanswered.remove(line)
        count = len(line) - 1 + (2 if line.startswith(b"{") else 1)
        reply = _echo(line) if body is None else body
        self.feed(json.dumps({"r": reply, "f": [1, status, count]}))

    def answer_all(self, *, data: bool = True) -> int:
        """Answer every unanswered line, control lines first (the board runs them first)."""
        done = 0
        while True:
            pending = [x for x in self.unanswered if x.startswith(b"{")]
            if data:
                pending += [x for x in self.unanswered if not x.startswith(b"{")]
            if not pending:
                return done
            self.answer(pending[0])
            done += 1

    def connect(self, report: dict[str, Any] | None = None) -> None:
        """Banner, settings, the overrides, `{home:n}` and the first report: ready."""
        self.session.open()
        self.pump()
        self.feed(banner(self.fb))
        while not self.session.ready:
            line = self.unanswered[0]
            self.answer(line, _echo(line, report))
        self.clear()

    def report(self, **fields: Any) -> None:
        self.feed(json.dumps({"sr": fields}))

    def clear(self) -> None:
        self.written.clear()
        self.events.clear()

    # -- reading what happened -----------------------------------------------

    def lines(self, lane: Lane | None = None) -> list[bytes]:
        return [data for kind, data in self.written if lane is None or kind is lane]

    def settled(self, token: object) -> Settled | None:
        found = [e for e in self.events if isinstance(e, Settled) and e.token is token]
        assert len(found) <= 1, "a token is settled once"
        return found[0] if found else None

    def of(self, kind: type[Any]) -> list[Any]:
        return [e for e in self.events if isinstance(e, kind)]


def _single(data: bytes) -> bool:
    """A single-character control with its LF (`!`, `~`, `%`, 0x04, ...)."""
    return len(data) == 2 and data.endswith(b"\n") and data[:1] in b"!~%\x04\x05\x18"


# What a GET of these reads on a fresh board: homed, the newest build, overrides 1.0.
_GOT = {"home": 1, "fb": 101.06, "stat": 4} | dict.fromkeys(
    ("fro", "tro", "spo", "mfo", "mto", "sso"), 1.0
)


def _echo(line: bytes, report: dict[str, Any] | None = None) -> dict[str, Any]:
    """What g2core puts in an answer's body: the pairs of the line, with GETs filled in."""
    if line.startswith(b"$") and b"=" not in line:  # a text GET (`$stat`), answered in JSON
        key = line[1:].strip().decode()
        return {key: _GOT.get(key, 0)}
    if not line.startswith(b"{"):
        return {}
    body: dict[str, Any] = json.loads(line)
    for key, value in body.items():
        if value is None:
            body[key] = (report or REPORT) if key == "sr" else _GOT.get(key, 0)
    return body
