"""Every method of the control API (../shared/spec/api.md), wired to the daemon.

Parameters are pydantic models (unknown fields refused: -32602). Errors
keep their api.md codes: the machine layer's errors carry `code`, `message`
and `data`; names that cannot be a file or a machine are -32602; a missing
machine is 1001, a missing job or file 1004.

The additions to api.md, documented in docs/api.md: `file.upload` takes
`final`, `upload` and `offset` (chunks stay in their own staging until the
final one, a retry is idempotent), so a half-uploaded or mixed program is
never started; a full disk or the jobs quota is error 1009. api.md's own
chunks (`append: true` alone) continue what the same connection published
(appends.py).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections import Counter
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Annotated, Any, Final, Literal

import structlog
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from hostd import __version__
from hostd.api import openrpc
from hostd.api.appends import Appends, Chain
from hostd.api.files import InvalidData, JobsDir, NoSuchFileError, check_name, decode
from hostd.api.rpc import Methods, RpcError, encode_notification
from hostd.api.server import Client, current_client
from hostd.api.uploads import ChunkError, NoSuchUpload, StorageError
from hostd.daemon import Daemon
from hostd.machine import operations
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
from hostd.machine.guard import check_jog, check_send, send_maintenance
from hostd.machine.machine import Machine
from hostd.machine.preflight import analyze_for, plan_for, prepare_start, recovery_for
from hostd.protocol.commands import InvalidCommand, Realtime
from hostd.protocol.gcode import JOG_AXES
from hostd.protocol.numbers import MAX_DISTANCE, MAX_FEED, MIN_FEED
from hostd.protocol.settings import check_key, check_values

log = structlog.get_logger(__name__)

API_VERSION = 1
STORAGE: Final = 1009  # docs/api.md: the jobs directory is full, over its quota, or failing
TOPICS = ("status", "exception", "supervisor", "fault", "job", "console", "probe")
Topic = Literal["status", "exception", "supervisor", "fault", "job", "console", "probe"]
MachineId = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")]
SettingKey = Annotated[str, Field(min_length=1, max_length=16, pattern=r"^[A-Za-z0-9_]+$")]
SettingValue = bool | int | float | str  # bounded by hostd.protocol.settings.check_values
AXES = JOG_AXES
# Every number a client gives is a JSON number of its type (strict: no strings, no
# booleans, no 1.0 for an integer), finite, and bounded.
MAX_ID = 2**53 - 1  # job and subscription ids, line numbers: exact in every JSON reader
Id = Annotated[int, Field(strict=True, ge=1, le=MAX_ID)]
Distance = Annotated[
    float, Field(strict=True, allow_inf_nan=False, ge=-MAX_DISTANCE, le=MAX_DISTANCE)
]
Feed = Annotated[float, Field(strict=True, allow_inf_nan=False, ge=MIN_FEED, le=MAX_FEED)]
UploadId = Annotated[str, Field(pattern=r"^[0-9a-f]{32}$")]


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class MachineParams(Params):
    machine: MachineId


class OverrideParams(MachineParams):
    """Percentages; each optional, at least one."""

    feed: Annotated[int, Field(strict=True, ge=1, le=1000)] | None = None
    rapid: Annotated[int, Field(strict=True, ge=1, le=1000)] | None = None
    spindle: Annotated[int, Field(strict=True, ge=1, le=1000)] | None = None

    @model_validator(mode="after")
    def _something(self) -> OverrideParams:
        if self.feed is None and self.rapid is None and self.spindle is None:
            raise ValueError("give feed, rapid or spindle")
        return self


HomeAxis = Literal["x", "y", "z", "a", "b", "c"]
Speed = Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0, le=1_000_000)]


class HomeParams(MachineParams):
    """`axes`: which to home (absent: all); each once."""

    axes: Annotated[list[HomeAxis], Field(min_length=1, max_length=6)] | None = None

    @field_validator("axes")
    @classmethod
    def _once(cls, axes: list[str] | None) -> list[str] | None:
        if axes is not None and len(set(axes)) != len(axes):
            raise ValueError("each axis once")
        return axes


class ZeroParams(MachineParams):
    """`axes`: the work position each named axis should read now."""

    axes: Annotated[dict[HomeAxis, Distance], Field(min_length=1)]


class SpindleParams(MachineParams):
    state: Literal["cw", "ccw", "off"]
    speed: Speed | None = None


class SendParams(MachineParams):
    line: str
    timeout: Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0, le=3600)] = 10.0


class JogParams(MachineParams):
    """Distances in the machine's units, |d| <= MAX_DISTANCE; MIN_FEED <= feed <= MAX_FEED."""

    axes: dict[str, Distance]
    feed: Feed

    @field_validator("axes")
    @classmethod
    def _known_axes(cls, axes: dict[str, float]) -> dict[str, float]:
        if not axes:
            raise ValueError("at least one axis")
        unknown = sorted(set(axes) - set(AXES))
        if unknown:
            raise ValueError(f"unknown axes {unknown}: use {', '.join(AXES)}")
        return axes


class SettingsGetParams(MachineParams):
    keys: Annotated[list[SettingKey], Field(min_length=1, max_length=100)]

    @field_validator("keys")
    @classmethod
    def _readable(cls, keys: list[str]) -> list[str]:
        for key in keys:
            check_key(key, read=True)  # a GET of `clear` clears: refused (settings.RESERVED)
        return keys


class SettingsSetParams(MachineParams):
    values: Annotated[dict[SettingKey, SettingValue], Field(min_length=1, max_length=100)]

    @field_validator("values")
    @classmethod
    def _settings(cls, values: dict[str, SettingValue]) -> dict[str, SettingValue]:
        check_values(values)  # reserved names, case duplicates, numbers and text bounds
        return values


class FileName(Params):
    name: str

    @field_validator("name")
    @classmethod
    def _plain(cls, name: str) -> str:
        return check_name(name)


class UploadParams(FileName):
    data: str
    encoding: Literal["utf-8", "base64"] = "utf-8"
    append: bool = False
    final: bool = True
    upload: UploadId | None = None  # from the first chunk's answer; continues that upload
    offset: Annotated[int, Field(ge=0)] | None = None  # where this chunk's bytes start


class JobStartParams(MachineParams):
    file: str
    start_line: Id = 1
    # From start_line > 1: restore the modal state and approach safely first (false: the
    # raw skip, dangerous: docs/api.md). `force` runs a program that leaves the travel.
    restore: Annotated[bool, Field(strict=True)] = True
    force: Annotated[bool, Field(strict=True)] = False

    @field_validator("file")
    @classmethod
    def _plain(cls, name: str) -> str:
        return check_name(name)


class JobParams(Params):
    job: Id


class JobRecoveryParams(Params):
    """`job`: where that job should resume. Or `machine`, `file` and `line`: the plan
    job.start would send to resume that file at that line (what `hostd run --from` shows)."""

    job: Id | None = None
    machine: MachineId | None = None
    file: str | None = None
    line: Id | None = None

    @model_validator(mode="after")
    def _one_form(self) -> JobRecoveryParams:
        plan = (self.machine, self.file, self.line)
        if (self.job is None) == (None in plan) or (self.job is not None and plan != (None,) * 3):
            raise ValueError("give job, or machine, file and line")
        if self.file is not None:
            check_name(self.file)
        return self


class FileAnalyzeParams(Params):
    file: str
    machine: MachineId | None = None  # its dialect, speeds and travel; none: g2core's rules

    @field_validator("file")
    @classmethod
    def _plain(cls, name: str) -> str:
        return check_name(name)


class JobListParams(Params):
    machine: MachineId | None = None
    limit: Annotated[int, Field(strict=True, ge=1, le=1000)] = 50


class FaultParams(MachineParams):
    fault: str


class FaultOverrideParams(FaultParams):
    override: bool


class SubscribeParams(Params):
    topics: Annotated[list[Topic], Field(min_length=1)]
    machine: MachineId | None = None


class UnsubscribeParams(Params):
    subscription: Id


Send = Callable[[bytes], object]


@dataclass(frozen=True, slots=True)
class _Subscription:
    owner: object  # the client: one notification per client, however many subscriptions match
    send: Send  # the client's send_line: takes an encoded message
    topics: frozenset[str]
    machine: str | None


# Subscriptions one client may hold, and all clients together (docs/api.md): a tab that
# subscribes in a loop must not make every notification cost a walk over thousands.
MAX_SUBSCRIPTIONS_PER_CLIENT = 32
MAX_SUBSCRIPTIONS = 4096


SUBSCRIPTIONS_FULL = -32000  # the server's range: as a daemon full of clients

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

    def add(self, owner: object, send: Send, topics: list[str], machine: str | None) -> int:
        """A new subscription's id. Raises RpcError(-32000) past either bound."""
        if self._owned[id(owner)] >= self.max_per_client:
            why = f"subscription limit: {self.max_per_client} per client; unsubscribe first"
            raise RpcError(SUBSCRIPTIONS_FULL, why)
        if len(self._subs) >= self.max_total:
            raise RpcError(SUBSCRIPTIONS_FULL, f"subscription limit: {self.max_total} in all")
        self._owned[id(owner)] += 1
        sub_id = self._next
        self._next += 1
        sub = _Subscription(owner, send, frozenset(topics), machine)
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


class Api:
    def __init__(self, daemon: Daemon, *, clock: Callable[[], float] = time.monotonic) -> None:
        self.daemon = daemon
        settings = daemon.config.daemon
        self.jobs = JobsDir(
            daemon.jobs_dir,
            quota=settings.jobs_quota,
            expiry=settings.upload_expiry,
            clock=clock,
        )
        self.subscriptions = Subscriptions(self._console_interest)
        self.appends = Appends()
        self.methods: Methods | None = None  # the table build_methods made, for rpc.discover
        self._discovered: dict[str, Any] | None = None

    def _console_interest(self) -> None:
        """Engines publish their raw traffic only while someone listens to it."""
        for machine in self.daemon.machines.values():
            machine.engine.console = self.subscriptions.wants("console", machine.id)

    def attach(self) -> None:
        """Listen to every machine (call once the daemon has built them)."""
        for machine in self.daemon.machines.values():
            machine.hub.subscribe(partial(self._on_event, machine))

    # -- events to topics ------------------------------------------------

    def _on_event(self, machine: Machine, event: Event) -> None:
        subs = self.subscriptions
        mid = machine.id
        if isinstance(event, Console):  # first: two a line while someone listens
            if subs.wants("console", mid):
                subs.deliver_line("console", mid, console_notification(event))
        elif isinstance(event, StatusChanged):
            if subs.wants("status", mid):
                snapshot = machine.snapshot()
                subs.deliver(
                    "status", mid, {"machine": mid, "report": event.report, "snapshot": snapshot}
                )
        elif isinstance(event, ExceptionRaised):
            subs.deliver("exception", mid, {"machine": mid, "report": event.report})
        elif isinstance(event, ProbeReported):
            subs.deliver(
                "probe", mid, {"machine": mid, "report": event.report, "probe": event.probe}
            )
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

    # -- helpers -----------------------------------------------------------

    def _machine(self, machine_id: str) -> Machine:
        machine = self.daemon.machine(machine_id)
        if machine is None:
            raise RpcError(1001, f"unknown machine {machine_id!r}")
        return machine

    async def _store(self) -> Any:
        store = self.daemon.store
        if store is None:
            raise RpcError(-32603, "the job store is not open")
        return store

    # -- daemon and machines ---------------------------------------------

    async def rpc_discover(self) -> dict[str, Any]:
        """This API as an OpenRPC document, made from the method table (hostd/api/openrpc.py)."""
        if self._discovered is None:
            assert self.methods is not None, "build_methods has not run"
            self._discovered = openrpc.document(self.methods, version=__version__, api=API_VERSION)
        return self._discovered

    async def daemon_info(self) -> dict[str, Any]:
        return {"version": __version__, "api": API_VERSION, "machines": list(self.daemon.machines)}

    async def machine_list(self) -> list[dict[str, Any]]:
        out = []
        for machine in self.daemon.machines.values():
            snap = machine.snapshot()
            out.append(
                {
                    "id": machine.id,
                    "dialect": machine.config.dialect,
                    "supervisor": snap["supervisor"],
                    "state": snap["state"],
                }
            )
        return out

    async def machine_status(self, p: MachineParams) -> dict[str, Any]:
        return self._machine(p.machine).snapshot()

    async def machine_connect(self, p: MachineParams) -> dict[str, Any]:
        machine = self._machine(p.machine)
        await machine.connect()
        return machine.snapshot()

    async def machine_disconnect(self, p: MachineParams) -> dict[str, Any]:
        machine = self._machine(p.machine)
        await machine.disconnect()
        return machine.snapshot()

    async def machine_send(self, p: SendParams) -> dict[str, Any]:
        machine = self._machine(p.machine)
        try:
            check_send(machine, p.line)  # maintenance commands: machine.maintenance only
            response = await machine.engine.send(p.line, timeout=p.timeout)
        except InvalidCommand as exc:
            raise RpcError(-32602, exc.message, exc.data) from None
        return {"status": response.status, "r": response.body}

    async def machine_maintenance(self, p: SendParams) -> dict[str, Any]:
        """One maintenance command, on purpose, where the machine's config allows it."""
        machine = self._machine(p.machine)
        try:
            response = await send_maintenance(machine, p.line, p.timeout)
        except InvalidCommand as exc:
            raise RpcError(-32602, exc.message, exc.data) from None
        return {"status": response.status, "r": response.body}

    async def machine_feedhold(self, p: MachineParams) -> dict[str, Any]:
        self._machine(p.machine).feedhold()
        return {}

    async def machine_cycle_start(self, p: MachineParams) -> dict[str, Any]:
        self._machine(p.machine).cycle_start()
        return {}

    async def machine_queue_flush(self, p: MachineParams) -> dict[str, Any]:
        self._machine(p.machine).engine.realtime(Realtime.QUEUE_FLUSH)
        return {}

    async def machine_job_kill(self, p: MachineParams) -> dict[str, Any]:
        self._machine(p.machine).engine.realtime(Realtime.JOB_KILL)
        return {}

    async def machine_reset(self, p: MachineParams) -> dict[str, Any]:
        await self._machine(p.machine).reset()
        return {}

    async def machine_clear(self, p: MachineParams) -> dict[str, Any]:
        await self._machine(p.machine).engine.clear()
        return {}

    async def machine_alarm(self, p: MachineParams) -> dict[str, Any]:
        await self._machine(p.machine).engine.alarm()  # refused where the dialect has none
        return {}

    async def machine_shutdown(self, p: MachineParams) -> dict[str, Any]:
        await self._machine(p.machine).engine.shutdown()
        return {}

    async def machine_jog(self, p: JogParams) -> dict[str, Any]:
        machine = self._machine(p.machine)
        try:
            check_jog(machine, p.axes)
        except InvalidCommand as exc:
            raise RpcError(-32602, exc.message, exc.data) from None
        job = await machine.jog(p.axes, p.feed)
        return {"job": job.id}

    async def machine_override(self, p: OverrideParams) -> dict[str, Any]:
        self._machine(p.machine).engine.override(p.feed, p.rapid, p.spindle)
        return {}

    async def machine_home(self, p: HomeParams) -> dict[str, Any]:
        await _operation(operations.home(self._machine(p.machine), _names(p.axes)))
        return {}

    async def machine_zero(self, p: ZeroParams) -> dict[str, Any]:
        machine = self._machine(p.machine)
        await _operation(operations.zero(machine, {str(a): v for a, v in p.axes.items()}))
        return machine.snapshot()

    async def machine_goto_zero(self, p: HomeParams) -> dict[str, Any]:
        await _operation(operations.goto_zero(self._machine(p.machine), _names(p.axes)))
        return {}

    async def machine_spindle(self, p: SpindleParams) -> dict[str, Any]:
        await _operation(operations.spindle(self._machine(p.machine), p.state, p.speed))
        return {}

    async def machine_override_in_force(self, p: OverrideParams) -> dict[str, Any]:
        """machine.override: grbl's realtime bytes, then the overrides the board reports."""
        machine = self._machine(p.machine)
        return await operations.override(machine, p.feed, p.rapid, p.spindle)

    async def machine_safety_door(self, p: MachineParams) -> dict[str, Any]:
        self._machine(p.machine).engine.safety_door()
        return {}

    async def machine_jog_stop(self, p: MachineParams) -> dict[str, Any]:
        self._machine(p.machine).jog_stop()
        return {}

    async def settings_get(self, p: SettingsGetParams) -> dict[str, Any]:
        return await self._machine(p.machine).read_settings(list(p.keys))

    async def settings_set(self, p: SettingsSetParams) -> dict[str, Any]:
        _, bodies = await self._machine(p.machine).write_settings(dict(p.values))
        return _merge(bodies) or dict(p.values)  # grbl answers a `$N=V` with a bare ok

    # -- files ---------------------------------------------------------------

    async def file_upload(self, p: UploadParams) -> dict[str, Any]:
        chain = self._chain()
        async with chain.lock if chain is not None else contextlib.nullcontext():
            return await self._upload(p, chain)

    def _chain(self) -> Chain | None:
        """The calling connection's uploads (appends.py); None without a connection (MQTT)."""
        try:
            client: Client = current_client()
        except LookupError:
            return None
        return self.appends.of(client)

    async def _upload(self, p: UploadParams, chain: Chain | None) -> dict[str, Any]:
        by_name = p.append and p.upload is None and p.offset is None  # api.md's own chunks
        try:
            data = decode(p.data, p.encoding)
            done = await asyncio.to_thread(
                self.jobs.upload,
                p.name,
                data,
                append=p.append,
                final=p.final,
                upload_id=p.upload,
                offset=p.offset,
                by_name=by_name,
                after=chain.last(p.name) if by_name and chain is not None else None,
            )
        except InvalidData as exc:
            raise RpcError(-32602, str(exc)) from None
        except ChunkError as exc:
            raise RpcError(-32602, str(exc), {"expected_offset": exc.expected}) from None
        except NoSuchUpload as exc:
            raise RpcError(1004, str(exc)) from None
        except StorageError as exc:
            log.warning("upload refused", file=p.name, reason=exc.reason, error=exc.message)
            raise RpcError(STORAGE, exc.message, {"reason": exc.reason}) from None
        if chain is not None and done.version is not None:
            chain.published(done.name, done.version)
        result: dict[str, Any] = {"name": done.name, "size": done.size}
        if done.upload is not None:
            result["upload"] = done.upload
        return result

    async def expire_uploads(self, every: float) -> None:
        """Remove abandoned uploads every `every` seconds, for as long as the daemon runs.

        Each upload call also expires them first; this frees the disk of an
        upload nobody comes back to, even when no other upload follows.
        """
        while True:
            await asyncio.sleep(every)
            try:
                removed = await asyncio.to_thread(self.jobs.uploads.expire)
            except OSError as exc:  # the next round may do better; the daemon goes on
                log.warning("cannot look for abandoned uploads", error=str(exc))
                continue
            for upload in removed:
                log.info("removed an abandoned upload", upload=upload)

    async def file_list(self) -> list[dict[str, Any]]:
        files = await asyncio.to_thread(self.jobs.entries)
        return [{"name": f.name, "size": f.size, "modified": f.modified} for f in files]

    async def file_delete(self, p: FileName) -> dict[str, Any]:
        try:
            await asyncio.to_thread(self.jobs.delete, p.name)
        except NoSuchFileError as exc:
            raise RpcError(1004, str(exc)) from None
        return {}

    # -- jobs ------------------------------------------------------------------

    async def job_start(self, p: JobStartParams) -> dict[str, Any]:
        machine = self._machine(p.machine)
        path = await self._resolve(p.file)
        preamble = await prepare_start(
            machine, path, p.start_line, restore=p.restore, force=p.force, pool=self.daemon.workers
        )
        job = await machine.start_make(p.file, p.start_line, preamble)
        return {"job": job.id, "preamble": preamble}

    async def _resolve(self, name: str) -> Path:
        """A file of the jobs directory, or 1004."""
        try:
            return await asyncio.to_thread(self.jobs.resolve, name)
        except NoSuchFileError as exc:
            raise RpcError(1004, str(exc)) from None

    async def file_analyze(self, p: FileAnalyzeParams) -> dict[str, Any]:
        path = await self._resolve(p.file)
        machine = None if p.machine is None else self._machine(p.machine)
        return (await analyze_for(machine, path, pool=self.daemon.workers)).to_json()

    async def job_recovery(self, p: JobRecoveryParams) -> dict[str, Any]:
        if p.job is None:
            assert p.machine is not None and p.file is not None and p.line is not None
            machine = self._machine(p.machine)
            path = await self._resolve(p.file)
            plan = await plan_for(machine, path, p.line, pool=self.daemon.workers)
            return {**plan.to_json(), "machine": p.machine, "file": p.file}
        job = await (await self._store()).get(p.job)
        if job is None:
            raise RpcError(1004, f"no job {p.job}")
        machine = self._machine(job.machine)
        path = self.jobs.path / (job.file or "")
        plan, about = await recovery_for(machine, path, job, pool=self.daemon.workers)
        result = plan.to_json()
        result.update(
            job=job.id,
            machine=job.machine,
            file=job.file,
            line_executed=job.line_executed,
            lines_acked=job.lines_acked,
            uncertain=about + plan.uncertain,
        )
        return result

    async def job_pause(self, p: MachineParams) -> dict[str, Any]:
        return self._machine(p.machine).pause().model_dump(mode="json")

    async def job_resume(self, p: MachineParams) -> dict[str, Any]:
        return self._machine(p.machine).resume().model_dump(mode="json")

    async def job_cancel(self, p: MachineParams) -> dict[str, Any]:
        job = await self._machine(p.machine).cancel()
        return job.model_dump(mode="json")

    async def job_get(self, p: JobParams) -> dict[str, Any]:
        for machine in self.daemon.machines.values():
            current = machine.current_job()
            if current is not None and current.id == p.job:
                return current.model_dump(mode="json")
        job = await (await self._store()).get(p.job)
        if job is None:
            raise RpcError(1004, f"no job {p.job}")
        return dict(job.model_dump(mode="json"))

    async def job_list(self, p: JobListParams) -> list[dict[str, Any]]:
        if p.machine is not None:
            self._machine(p.machine)
        jobs = await (await self._store()).list_jobs(p.machine, p.limit)
        live = {
            job.id: job
            for m in self.daemon.machines.values()
            if (job := m.current_job()) is not None
        }
        return [live.get(j.id, j).model_dump(mode="json") for j in jobs]

    # -- faults ------------------------------------------------------------

    async def fault_list(self, p: MachineParams) -> list[dict[str, Any]]:
        return [f.to_json() for f in self._machine(p.machine).faults.all()]

    async def fault_override(self, p: FaultOverrideParams) -> dict[str, Any]:
        return self._machine(p.machine).override_fault(p.fault, p.override).to_json()

    async def fault_clear(self, p: FaultParams) -> dict[str, Any]:
        return self._machine(p.machine).clear_fault(p.fault).to_json()

    # -- subscriptions -----------------------------------------------------

    async def subscribe_client(self, p: SubscribeParams) -> dict[str, Any]:
        """Topics for the calling client, delivered through its bounded queue until it leaves."""
        if p.machine is not None:
            self._machine(p.machine)
        client = current_client()
        if not self.subscriptions.has(client):
            client.on_disconnect.append(partial(self.subscriptions.remove_all, client))
        sub_id = self.subscriptions.add(client, client.send_line, list(p.topics), p.machine)
        if client.closed:  # it left while this request ran: its hooks may have run already
            self.subscriptions.remove_all(client)
        return {"subscription": sub_id}

    async def unsubscribe(self, p: UnsubscribeParams) -> dict[str, Any]:
        # A client ends its own subscriptions only: another's id is as unknown as a bad one.
        if not self.subscriptions.remove(p.subscription, owner=current_client()):
            raise RpcError(-32602, f"no subscription {p.subscription}")
        return {}


def _names(axes: list[HomeAxis] | None) -> list[str] | None:
    return None if axes is None else [str(a) for a in axes]


async def _operation(run: Awaitable[None]) -> None:
    """An operation of hostd.machine.operations; a refused line is -32602, as in machine.send."""
    try:
        await run
    except InvalidCommand as exc:
        raise RpcError(-32602, exc.message, exc.data) from None


def _merge(bodies: list[dict[str, Any]]) -> dict[str, Any]:
    merged: dict[str, Any] = {}
    for body in bodies:
        merged.update(body)
    return merged


def build_methods(api: Api) -> Methods:
    """The api.md method table, name by name."""
    m = Methods()
    m.register("rpc.discover", None, api.rpc_discover)
    m.register("daemon.info", None, api.daemon_info)
    m.register("machine.list", None, api.machine_list)
    m.register("machine.status", MachineParams, api.machine_status)
    m.register("machine.connect", MachineParams, api.machine_connect)
    m.register("machine.disconnect", MachineParams, api.machine_disconnect)
    m.register("machine.send", SendParams, api.machine_send)
    m.register("machine.maintenance", SendParams, api.machine_maintenance)
    m.register("machine.feedhold", MachineParams, api.machine_feedhold, immediate=True)
    m.register("machine.cycle_start", MachineParams, api.machine_cycle_start, immediate=True)
    m.register("machine.queue_flush", MachineParams, api.machine_queue_flush, immediate=True)
    m.register("machine.job_kill", MachineParams, api.machine_job_kill, immediate=True)
    m.register("machine.reset", MachineParams, api.machine_reset)
    m.register("machine.clear", MachineParams, api.machine_clear)
    m.register("machine.alarm", MachineParams, api.machine_alarm)
    m.register("machine.shutdown", MachineParams, api.machine_shutdown)
    m.register("machine.jog", JogParams, api.machine_jog)
    m.register("machine.jog_stop", MachineParams, api.machine_jog_stop, immediate=True)
    # Not immediate: it waits for the report that shows the overrides now in force.
    m.register("machine.override", OverrideParams, api.machine_override_in_force)
    m.register("machine.home", HomeParams, api.machine_home)
    m.register("machine.zero", ZeroParams, api.machine_zero)
    m.register("machine.goto_zero", HomeParams, api.machine_goto_zero)
    m.register("machine.spindle", SpindleParams, api.machine_spindle)
    m.register("machine.safety_door", MachineParams, api.machine_safety_door, immediate=True)
    m.register("settings.get", SettingsGetParams, api.settings_get)
    m.register("settings.set", SettingsSetParams, api.settings_set)
    m.register("file.upload", UploadParams, api.file_upload)
    m.register("file.list", None, api.file_list)
    m.register("file.delete", FileName, api.file_delete)
    m.register("job.start", JobStartParams, api.job_start)
    m.register("job.pause", MachineParams, api.job_pause)
    m.register("job.resume", MachineParams, api.job_resume)
    m.register("job.cancel", MachineParams, api.job_cancel)
    m.register("job.get", JobParams, api.job_get)
    m.register("job.list", JobListParams, api.job_list)
    m.register("job.recovery", JobRecoveryParams, api.job_recovery)
    m.register("file.analyze", FileAnalyzeParams, api.file_analyze)
    m.register("fault.list", MachineParams, api.fault_list)
    m.register("fault.override", FaultOverrideParams, api.fault_override)
    m.register("fault.clear", FaultParams, api.fault_clear)
    m.register("subscribe", SubscribeParams, api.subscribe_client)
    m.register("unsubscribe", UnsubscribeParams, api.unsubscribe)
    api.methods = m
    return m
