"""Every row of the supervisor's table, and every event that does not fit."""

from __future__ import annotations

import pytest

from hostd.machine.supervisor import TRANSITIONS, Event, Refused, State, Supervisor, Transition

E, S = Event, State

EXPECTED = {
    (S.DISCONNECTED, E.CONNECT): S.BUSY,
    (S.BUSY, E.DISCONNECT): S.DISCONNECTED,
    (S.IDLE, E.DISCONNECT): S.DISCONNECTED,
    (S.OPERATION, E.DISCONNECT): S.DISCONNECTED,
    (S.PAUSED, E.DISCONNECT): S.DISCONNECTED,
    (S.BUSY, E.DISCONNECTED): S.DISCONNECTED,
    (S.IDLE, E.DISCONNECTED): S.DISCONNECTED,
    (S.OPERATION, E.DISCONNECTED): S.DISCONNECTED,
    (S.PAUSED, E.DISCONNECTED): S.DISCONNECTED,
    (S.BUSY, E.WENT_IDLE): S.IDLE,
    (S.IDLE, E.WENT_BUSY): S.BUSY,
    (S.IDLE, E.START_OPERATION): S.OPERATION,
    (S.OPERATION, E.PAUSE_OPERATION): S.PAUSED,
    (S.PAUSED, E.UNPAUSE_OPERATION): S.OPERATION,
    (S.OPERATION, E.OPERATION_STOPPED): S.BUSY,
    (S.PAUSED, E.OPERATION_STOPPED): S.BUSY,
}


def test_the_table_is_behaviour_md() -> None:
    assert TRANSITIONS == EXPECTED


@pytest.mark.parametrize(("source", "event"), list(EXPECTED))
def test_each_transition_is_taken_and_published(source: State, event: Event) -> None:
    seen: list[Transition] = []
    sup = Supervisor(seen.append)
    sup.state = source
    transition = sup.fire(event)
    assert sup.state is EXPECTED[(source, event)]
    assert seen == [transition] == [Transition(source, sup.state, event)]


@pytest.mark.parametrize(
    ("source", "event"),
    [(s, e) for s in State for e in Event if (s, e) not in EXPECTED],
)
def test_an_event_that_does_not_fit_is_refused_whole(source: State, event: Event) -> None:
    seen: list[Transition] = []
    sup = Supervisor(seen.append)
    sup.state = source
    assert not sup.can(event)
    with pytest.raises(Refused) as err:
        sup.fire(event)
    assert err.value.code == 1003
    assert event.value in err.value.message and source.value in err.value.message
    assert sup.state is source
    assert seen == []
