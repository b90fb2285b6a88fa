"""Who gets which notification: topics per client, fanned out without blocking.

`publish` turns a machine's events into api.md's notifications; a
`Subscriptions` table says which clients want them. `subscribe` and
`unsubscribe` are the methods that change it.
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import Field

from hostd.api.client import current_client
from hostd.api.methods.params import Id, MachineId, Params
from hostd.api.rpc import SERVER_FULL, Methods, RpcError, encode_notification
from hostd.machine.events import (
    Console,
    Event,
    ExceptionRaised,
    FaultChanged,
    JobChanged,
    ProbeReported,
    StatusChanged,
    SupervisorChanged,
)
from hostd.machine.machine import Machine

if TYPE_CHECKING:
    from hostd.api.methods.base import Api

TOPICS = ("status", "exception", "supervisor", "fault", "job", "console", "probe")
Topic = Literal["status", "exception", "supervisor", "fault", "job", "console", "probe"]


# Where a running job's own console lines go: the `console` subscriptions that did not
# ask to leave them out (`job_lines: false`). Not a topic a client names; a routing key.
JOB_LINES = "console.job"
# Where the host's status polls and the board's status reports go among console lines: the
# `console` subscriptions that did not ask to leave them out (`status_traffic: false`).
STATUS_LINES = "console.status"


class SubscribeParams(Params):
    topics: Annotated[list[Topic], Field(min_length=1)]
    machine: MachineId | None = None
    # An addition to api.md's `subscribe` (optional, default as api.md says): false leaves a
    # running job's own lines, and the board's plain answers to them, out of `console`.
    job_lines: Annotated[
        bool,
        Field(
            strict=True,
            description="false: `console` leaves out a running job's own lines and the "
            "board's plain answers to them (docs/api.md, Additions)",
        ),
    ] = True
    # Another addition (optional, default as api.md says): false leaves the host's status
    # polls and the board's status reports out of `console`.
    status_traffic: Annotated[
        bool,
        Field(
            strict=True,
            description="false: `console` leaves out the host's status polls and the "
            "board's status reports, which the `status` topic carries (docs/api.md, Additions)",
        ),
    ] = True


class UnsubscribeParams(Params):
    subscription: Id


Send = Callable[[bytes], object]


@dataclass(frozen=True, slots=True)
class _Subscription:
    owner: object  # the client: one notification per client, however many subscriptions match
    send: Send  # the client's send_notice: takes an encoded message
    topics: frozenset[str]
    machine: str | None


# Subscriptions one client may hold, and all clients together (docs/api.md): a tab that
# subscribes in a loop must not make every notification cost a walk over thousands.
MAX_SUBSCRIPTIONS_PER_CLIENT = 32
MAX_SUBSCRIPTIONS = 4096

# A str as a JSON string, non-ASCII kept (the C encoder rpc.encode's ensure_ascii=False uses).
_json_string: Callable[[str], str] = json.encoder.encode_basestring


class Subscriptions:
    """Which client wants which topics of which machine; fan-out never blocks.

    A notification is encoded once, however many clients get it, and not at
    all when nobody wants it; the same bytes go to every subscriber's queue.
    `wants` is a dictionary look-up, since it is asked for every status report
    of every machine. Bounded: `max_per_client` per owner, `max_total` in all.
    """

    def __init__(
        self,
        on_change: Callable[[], None] | None = None,
        *,
        max_per_client: int = MAX_SUBSCRIPTIONS_PER_CLIENT,
        max_total: int = MAX_SUBSCRIPTIONS,
    ) -> None:
        self._next = 1
        self._subs: dict[int, _Subscription] = {}
        self._interest: Counter[tuple[str, str | None]] = Counter()
        self._owned: Counter[int] = Counter()  # id(owner) -> subscriptions it holds
        # (topic, machine) -> each matching owner's send, once: rebuilt after any change.
        self._sends: dict[tuple[str, str], list[Send]] = {}
        self._on_change = on_change
        self.max_per_client = max_per_client
        self.max_total = max_total

    def __len__(self) -> int:
        return len(self._subs)

    def add(
        self,
        owner: object,
        send: Send,
        topics: list[str],
        machine: str | None,
        *,
        job_lines: bool = True,
        status_traffic: bool = True,
    ) -> int:
        """A new subscription's id. Raises RpcError(-32000) past either bound.

        A `console` subscription gets a running job's own lines (the `JOB_LINES`
        routing key) unless `job_lines` is False, and the status polls and reports
        (`STATUS_LINES`) unless `status_traffic` is False.
        """
        if self._owned[id(owner)] >= self.max_per_client:
            why = f"subscription limit: {self.max_per_client} per client; unsubscribe first"
            raise RpcError(SERVER_FULL, why)
        if len(self._subs) >= self.max_total:
            raise RpcError(SERVER_FULL, f"subscription limit: {self.max_total} in all")
        self._owned[id(owner)] += 1
        sub_id = self._next
        self._next += 1
        keys = set(topics)
        if job_lines and "console" in keys:
            keys.add(JOB_LINES)
        if status_traffic and "console" in keys:
            keys.add(STATUS_LINES)
        sub = _Subscription(owner, send, frozenset(keys), machine)
        self._subs[sub_id] = sub
        self._interest.update((topic, machine) for topic in sub.topics)
        self._changed()
        return sub_id

    def remove(self, sub_id: int, owner: object | None = None) -> bool:
        """Ends a subscription; with `owner`, only one of that owner's (another's is not found)."""
        sub = self._subs.get(sub_id)
        if sub is None or (owner is not None and sub.owner is not owner):
            return False
        del self._subs[sub_id]
        self._owned[id(sub.owner)] -= 1
        if self._owned[id(sub.owner)] <= 0:
            del self._owned[id(sub.owner)]
        self._interest.subtract((topic, sub.machine) for topic in sub.topics)
        self._changed()
        return True

    def remove_all(self, owner: object) -> None:
        for sub_id in [k for k, sub in self._subs.items() if sub.owner is owner]:
            self.remove(sub_id)

    def has(self, owner: object) -> bool:
        return any(sub.owner is owner for sub in self._subs.values())

    def wants(self, topic: str, machine: str) -> bool:
        interest = self._interest  # .get: a Counter's [] calls __missing__ for a zero
        return interest.get((topic, None), 0) > 0 or interest.get((topic, machine), 0) > 0

    def deliver(self, topic: str, machine: str, params: dict[str, Any]) -> None:
        if self.wants(topic, machine):
            self.deliver_line(topic, machine, encode_notification(topic, params))

    def deliver_line(self, topic: str, machine: str, line: bytes) -> None:
        """A notification already encoded, to every client that wants it."""
        sends = self._sends.get((topic, machine))
        if sends is None:
            sends = self._sends[(topic, machine)] = self._recipients(topic, machine)
        for send in sends:  # (a send may end a subscription: this list stays as it was)
            send(line)

    def _recipients(self, topic: str, machine: str) -> list[Send]:
        done: set[int] = set()
        sends: list[Send] = []
        for sub in self._subs.values():
            if _matches(sub, topic, machine) and id(sub.owner) not in done:
                done.add(id(sub.owner))
                sends.append(sub.send)
        return sends

    def _changed(self) -> None:
        self._sends = {}
        if self._on_change is not None:
            self._on_change()


def _matches(sub: _Subscription, topic: str, machine: str) -> bool:
    return topic in sub.topics and sub.machine in (None, machine)


def console_notification(event: Console) -> bytes:
    """The `console` notification, as `encode_notification` writes it, but made by hand.

    Two a line streamed while the console topic has a listener: the general
    encoder's walk over a dictionary cost more than the line's own path
    (docs/performance.md, issue 30). Text that has no UTF-8 form (a lone
    surrogate) goes the general way, which escapes it.
    """
    text = "".join(
        (
            '{"jsonrpc":"2.0","method":"console","params":{"machine":',
            _json_string(event.machine),
            ',"direction":',
            _json_string(event.direction),
            ',"channel":',
            _json_string(event.channel),
            ',"text":',
            _json_string(event.text),
            "}}",
        )
    )
    try:
        return text.encode()
    except UnicodeEncodeError:
        params = {
            "machine": event.machine,
            "direction": event.direction,
            "channel": event.channel,
            "text": event.text,
        }
        return encode_notification("console", params)


def publish(subs: Subscriptions, machine: Machine, event: Event) -> None:
    """One machine event as the notification of its topic, to whoever wants it."""
    mid = machine.id
    if isinstance(event, Console):  # first: two a line while someone listens
        key = JOB_LINES if event.job else STATUS_LINES if event.status else "console"
        if subs.wants(key, mid):
            subs.deliver_line(key, mid, console_notification(event))
    elif isinstance(event, StatusChanged):
        if subs.wants("status", mid):
            snapshot = machine.snapshot()
            subs.deliver(
                "status", mid, {"machine": mid, "report": event.report, "snapshot": snapshot}
            )
    elif isinstance(event, ExceptionRaised):
        subs.deliver("exception", mid, {"machine": mid, "report": event.report})
    elif isinstance(event, ProbeReported):
        subs.deliver("probe", mid, {"machine": mid, "report": event.report, "probe": event.probe})
    elif isinstance(event, SupervisorChanged):
        subs.deliver(
            "supervisor",
            mid,
            {"machine": mid, "from": event.source, "to": event.target, "event": event.event},
        )
    elif isinstance(event, JobChanged):
        subs.deliver("job", mid, {"machine": mid, "job": event.job})
    elif isinstance(event, FaultChanged):
        subs.deliver("fault", mid, {"machine": mid, "fault": event.fault})


class SubscriptionMethods:
    def __init__(self, api: Api) -> None:
        self.api = api

    async def subscribe_client(self, p: SubscribeParams) -> dict[str, Any]:
        """Topics for the calling client, delivered through its bounded queue until it leaves.

        `job_lines` (optional, default true; an addition to api.md): false leaves a
        running job's own lines, and the board's plain answers to them (status 0),
        out of this subscription's `console` topic; every other line still comes
        (the operator's commands, queries, errors, alarms, status traffic). A
        dashboard follows the job by the `job` topic's progress instead: at a
        laser's 1,000-2,000 lines a second, the job's lines were two console
        notifications a line that nobody could read.

        `status_traffic` (optional, default true; another addition): false leaves
        the host's status polls and the board's status reports out of `console`;
        the `status` topic carries what they say. The dashboard hid them in the
        browser, several a second on every machine, after the daemon had made and
        sent each one.
        """
        if p.machine is not None:
            self.api.machine(p.machine)
        client = current_client()
        if not self.api.subscriptions.has(client):
            client.on_disconnect.append(partial(self.api.subscriptions.remove_all, client))
        sub_id = self.api.subscriptions.add(
            client,
            client.send_notice,
            list(p.topics),
            p.machine,
            job_lines=p.job_lines,
            status_traffic=p.status_traffic,
        )
        if client.closed:  # it left while this request ran: its hooks may have run already
            self.api.subscriptions.remove_all(client)
        return {"subscription": sub_id}

    async def unsubscribe(self, p: UnsubscribeParams) -> dict[str, Any]:
        # A client ends its own subscriptions only: another's id is as unknown as a bad one.
        if not self.api.subscriptions.remove(p.subscription, owner=current_client()):
            raise RpcError(-32602, f"no subscription {p.subscription}")
        return {}


def register(m: Methods, api: Api) -> None:
    h = SubscriptionMethods(api)
    m.register("subscribe", SubscribeParams, h.subscribe_client)
    m.register("unsubscribe", UnsubscribeParams, h.unsubscribe)
