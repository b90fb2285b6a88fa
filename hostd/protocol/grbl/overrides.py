"""GrblSession's overrides: absolute percentages as relative bytes, by rounds.

A layer of `GrblSession` (session.py). grbl's override bytes are relative
steps, and neither firmware takes many at once (classic grbl one of a kind a
main-loop pass, grblHAL a 16-slot ring): `override` writes them in rounds
(`_Rounds`, `_override_round`), each followed by `?`s, until a report that
postdates the round's bytes shows the values asked (`_override_seen`), or a
round brings them no nearer (classic grbl; on grblHAL every round is from a
reset, and a bound of rounds ends it). OVERRIDE_ROUNDS, OVERRIDE_HAL_ROUNDS,
OVERRIDE_RING, UNASKED_REPORTS and OVERRIDE_ASKS bound it; `override`'s
docstring cites the firmware.
"""

from __future__ import annotations

from dataclasses import dataclass

from hostd.protocol.grbl import codec
from hostd.protocol.grbl.holds import GrblHolds
from hostd.protocol.vocabulary import Lane

# `?`s more after an override round while a report that postdates its bytes carries no
# `Ov:` and one may be due next (classic grbl defers it a report behind `WCO:`)
OVERRIDE_ASKS = 2

# Override rounds at most (`override`): the first, from a reset to 100, then steps from
# what the board reported. Classic grbl takes one byte of a kind a pass, so a round moves
# a feed or spindle override by one step of ten and one of one: 100 to any of 10..200 is
# at most 10 rounds, and any value to any other at most 19 (190 = 19 steps of ten);
# grblHAL takes 15 a ring a pass (the 19 bytes of 100 to 199 or 11: two rounds).
OVERRIDE_ROUNDS = 20

# grblHAL's override rings (override.h OVERRIDE_BUFSIZE 16, override.c:37-42: a byte
# arriving at a full ring is dropped): 15 usable. Feed and rapid share one (protocol.c:941-950).
OVERRIDE_RING = 15

# Reports grblHAL prints that no `?` asked for, one of which may come between the host's
# override bytes and the pass that reads them: its auto-report every `$481` ms
# (grbllib.c:160-167; the `?` is still answered besides, protocol.c:987-990), and the
# ones it forces as a homing cycle starts (motion_control.c:919-922) and as a tool change
# ends (state_machine.c:478-479). Classic grbl prints a report only for a `?`
# (gnea/grbl serial.c:152).
UNASKED_REPORTS = 1

# grblHAL's rounds are absolute (a reset, then steps): one is enough unless a byte was
# lost or the build has other bounds, or the round's report was read too early; more
# than this many means the board keeps other values.
OVERRIDE_HAL_ROUNDS = 3


@dataclass(slots=True)
class _Rounds:
    """A machine.override under way (`GrblSession.override`): what was asked, and its
    rounds so far."""

    wanted: dict[str, int]  # percent: feed, rapid, spindle, those asked
    rounds: int = 0  # rounds written
    hops: int = 0  # reports to read before one surely postdates the last round's bytes
    asks: int = 0  # `?`s left while such a report carries no `Ov:`
    gap: int | None = None  # how far from `wanted` the last round found the board
    final: bool = False  # the board was reset: the next `Ov:` is the answer

    def gap_to(self, now: dict[str, float]) -> int | None:
        """How far `now` is from the values asked (None: a value was never reported)."""
        if any(what not in now for what in self.wanted):
            return None
        return sum(abs(round(now[what]) - percent) for what, percent in self.wanted.items())


class GrblOverrides(GrblHolds):
    """machine.override by rounds (see `GrblSession`)."""

    def _unasked_reports(self) -> int:
        """Reports the board may print between the host's realtime bytes and the pass
        that reads them, no `?` asking (UNASKED_REPORTS: grblHAL's; classic grbl none)."""
        return UNASKED_REPORTS if self.flavour == "GrblHAL" else 0

    def override(
        self, feed: int | None = None, rapid: int | None = None, spindle: int | None = None
    ) -> None:
        """The override bytes (grbl.h CMD_OVERRIDE_*), by rounds, each followed by `?`s,
        until a report shows the values asked; then `override_answers` counts up.

        grbl's overrides are relative steps; an absolute percentage is a reset to
        100 then steps of 10 and of 1, all realtime bytes, taken in any state.
        Rapid has three settings: 100, 50 and 25; feed and spindle are refused
        outside 10..200, the firmware's own bounds.

        Neither firmware takes many at once. Classic grbl keeps one flag bit per
        kind (serial.c:167-181), applied once a main-loop pass (protocol.c:405-452):
        a reset and five "+10" that arrive within one pass make 110, not 150.
        grblHAL queues them in 16-slot rings (override.c:35-43), feed and rapid in
        one (protocol.c:941-950), and drops a byte that finds its ring full: the
        19 bytes of 100 to 199 lose their last. So a round writes what one pass
        takes (classic: one byte of a kind; grblHAL: OVERRIDE_RING a ring). On
        classic grbl the first is from a reset and the next ones step from what a
        report said, up to OVERRIDE_ROUNDS (`_Rounds`, `_override_round`). On
        grblHAL every round is from a reset, by the fewest steps, which a ring
        holds (`codec.override_from_reset`), up to OVERRIDE_HAL_ROUNDS: grblHAL
        prints reports nobody asked for (UNASKED_REPORTS), so a report the host
        takes for the round's may still predate its bytes, and a round that
        stepped from it would overshoot (asked 173, the upstream Simulator went
        to 200; docs/dialects.md). Written from a reset, the round sets the same
        values again.

        A `?` read in the same pass as the bytes is answered before they act
        (gnea/grbl protocol.c:250-253 before :405; grblHAL protocol.c:604-605
        before :629): the next round, or the answer, comes from a report asked
        after the one that answered that `?` (`_override_seen`). A round that
        brings no value nearer ends it: the answer is then what the board said,
        with a warning, never the values asked.
        """
        self._require_open()
        wanted: dict[str, int] = {}
        if feed is not None:
            codec.check_override(feed, "feed")
            wanted["feed"] = feed
        if rapid is not None:
            codec.rapid_override(rapid)
            wanted["rapid"] = rapid
        if spindle is not None:
            codec.check_override(spindle, "spindle")
            wanted["spindle"] = spindle
        self._override = _Rounds(wanted)
        self._override_round(None)

    def _override_round(self, now: dict[str, float] | None) -> None:
        """One round's bytes (see `override`), then a `?`: on classic grbl from a reset
        when `now`, the values the board last reported, is None (the first round), else
        steps from them; on grblHAL always from a reset (`codec.override_from_reset`).

        The bytes are realtime: they go now, whatever line waits. The report that
        answers the round's `?` may predate them, as may each that answers an older
        `?` still unanswered (`_asks_open`: a board reading slowly answers the ones the
        heartbeat asked again one by one), and on grblHAL one nobody asked for
        (UNASKED_REPORTS): `hops` reports are read, a `?` asked after each, before one
        surely postdates them.
        """
        rounds = self._override
        assert rounds is not None
        wanted = rounds.wanted
        hal = self.flavour == "GrblHAL"
        motion: list[bytes] = []  # feed and rapid: one ring on grblHAL
        accessory: list[bytes] = []
        if "rapid" in wanted and (now is None or now.get("rapid") != wanted["rapid"]):
            motion.append(codec.rapid_override(wanted["rapid"]))
        for what, ring in (("feed", motion), ("spindle", accessory)):
            if what not in wanted:
                continue
            value = None if now is None else now.get(what)
            start = None if value is None else int(value)
            if start is None or start != wanted[what]:
                if hal:  # absolute: a round read too early is written again, not overshot
                    ring += codec.override_from_reset(wanted[what], what, OVERRIDE_RING)
                else:
                    ring += codec.override_steps(wanted[what], what, start)
        if hal:
            motion, accessory = motion[:OVERRIDE_RING], accessory[:OVERRIDE_RING]
        else:  # one byte of a kind; in the order protocol.c applies them (reset, 10s, 1s)
            motion, accessory = list(dict.fromkeys(motion)), list(dict.fromkeys(accessory))
        self._out += [(Lane.REALTIME, b) for b in motion + accessory]
        rounds.rounds += 1
        # Each `?` still unanswered may bring a report that predates the bytes, so may
        # one nobody asked for (grblHAL), then the round's own may (same pass): the one
        # after those surely follows them.
        rounds.hops = 2 + self._asks_open() + self._unasked_reports()
        rounds.asks = OVERRIDE_ASKS
        self._ask_report()

    def _override_seen(self, report: codec.StatusReport, fresh: bool) -> None:
        """A report while an override's rounds run (`override`); `fresh`: it has `Ov:`."""
        rounds = self._override
        assert rounds is not None
        rounds.hops -= 1
        if rounds.hops > 0:
            self._ask_report()  # this report may predate the round's bytes: ask again
            return
        now = self.model.overrides
        if not fresh and rounds.asks and (now is None or "WCO" in report.fields):
            # No `Ov:`: with no change since the last one the board sends none for up
            # to 20 reports (report.c:615-619), but classic grbl also defers one a
            # report when it prints WCO (report.c:608): ask again.
            rounds.asks -= 1
            rounds.hops = 1
            self._ask_report()
            return
        gap = None if now is None else rounds.gap_to(now)
        why = None
        if gap == 0:
            pass
        elif gap is None:
            why = "the board reports no overrides"
        elif rounds.final:
            why = "the controller was reset meanwhile"
        elif self.flavour == "GrblHAL":
            # Each round sets the values whatever the board held: a round that brings
            # none nearer may have been read too early, and is written again.
            if rounds.rounds < OVERRIDE_HAL_ROUNDS:
                self._override_round(now)
                return
            why = f"not there after {OVERRIDE_HAL_ROUNDS} rounds"
        elif rounds.gap is not None and gap >= rounds.gap:
            why = "the last round brought them no nearer"
        elif rounds.rounds >= OVERRIDE_ROUNDS:
            why = f"not there after {OVERRIDE_ROUNDS} rounds"
        else:
            rounds.gap = gap
            self._override_round(now)
            return
        if why is not None:
            self._log.warning("overrides not as asked", asked=rounds.wanted, reported=now, why=why)
        self._override = None
        self.override_answers += 1
