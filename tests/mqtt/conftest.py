"""A real broker (Debian's mosquitto) on a free loopback port, and a subscriber to watch it.

The broker runs without persistence, so whatever is retained after a restart
was published again by the daemon. `.ci/run` installs mosquitto; without it
these tests fail (saying so), never skip: MQTT is tested against a real broker or not at all.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import os
import pwd
import shutil
import socket
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import aiomqtt
import pytest
import pytest_asyncio
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties
from paho.mqtt.subscribeoptions import SubscribeOptions

from hostd.api.methods import build_methods
from hostd.api.mqtt.bridge import MqttBridge
from hostd.api.mqtt.config import MqttConfig
from tests.daemon.conftest import Running, running_daemon

MOSQUITTO = shutil.which("mosquitto") or shutil.which("mosquitto", path="/usr/sbin:/sbin")
REQUEST_IDS = itertools.count(1)
# Seconds any one expected message may take before the test fails: a bound against a hang.
# A daemon process's first "online" waits for its start (imports, then the broker): past
# 15 s on a loaded two-core machine (load average 12-16).
WAIT = 30.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@dataclass
class Broker:
    """mosquitto on 127.0.0.1:`port`; `stop()` and `start()` again on the same port."""

    directory: Path
    port: int = field(default_factory=free_port)
    # Keep retained messages across a restart (saved at stop), as a production broker does.
    persistence: bool = False
    # Log every packet (mosquitto's `log_type debug`): what the broker received, in order.
    debug: bool = False
    log: list[str] = field(default_factory=list)
    _proc: asyncio.subprocess.Process | None = None
    _drain: asyncio.Task[None] | None = None

    @property
    def url(self) -> str:
        return f"mqtt://127.0.0.1:{self.port}"

    async def start(self) -> None:
        assert MOSQUITTO is not None
        conf = self.directory / "mosquitto.conf"
        conf.write_text(
            f"listener {self.port} 127.0.0.1\n"
            "allow_anonymous true\n"
            f"persistence {'true' if self.persistence else 'false'}\n"
            f"persistence_location {self.directory}/\n"
            # Started as root it would save as user `mosquitto`, who cannot reach tmp_path.
            f"user {pwd.getpwuid(os.geteuid()).pw_name}\n"
            "log_dest stderr\n"
            "log_type error\nlog_type warning\nlog_type notice\nlog_type information\n"
            + ("log_type debug\n" if self.debug else "")
        )
        self._proc = await asyncio.create_subprocess_exec(
            MOSQUITTO,
            "-c",
            str(conf),
            stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.DEVNULL,
            stderr=asyncio.subprocess.PIPE,
        )
        stream = self._proc.stderr
        assert stream is not None
        async with asyncio.timeout(WAIT):
            while True:
                line = (await stream.readline()).decode(errors="replace")
                if not line:
                    raise RuntimeError("mosquitto did not start:\n" + "".join(self.log))
                self.log.append(line)
                if " running" in line:  # "mosquitto version 2.0.11 running"
                    break
        self._drain = asyncio.create_task(self._keep_reading(stream))

    async def _keep_reading(self, stream: asyncio.StreamReader) -> None:
        while line := await stream.readline():
            self.log.append(line.decode(errors="replace"))

    async def stop(self) -> None:
        if self._proc is None:
            return
        if self._proc.returncode is None:
            self._proc.terminate()
        await self._proc.wait()
        if self._drain is not None:
            await self._drain
        self._proc = None


@pytest_asyncio.fixture
async def broker(tmp_path: Path) -> AsyncIterator[Broker]:
    if MOSQUITTO is None:
        pytest.fail("mosquitto is not installed: apt-get install mosquitto (.ci/run does)")
    directory = tmp_path / "broker"
    directory.mkdir()
    running = Broker(directory)
    await running.start()
    try:
        yield running
    finally:
        await running.stop()


class Watcher:
    """A stock MQTT client subscribed to a filter: every message, in order, with its flags."""

    def __init__(self, client: aiomqtt.Client) -> None:
        self.client = client
        self.messages: asyncio.Queue[aiomqtt.Message] = asyncio.Queue()
        self._task = asyncio.create_task(self._read())

    async def _read(self) -> None:
        async for message in self.client.messages:
            self.messages.put_nowait(message)

    async def next(self, predicate: Callable[[aiomqtt.Message], bool]) -> aiomqtt.Message:
        """The first message (from now on) that `predicate` accepts."""
        async with asyncio.timeout(WAIT):
            while True:
                message = await self.messages.get()
                if predicate(message):
                    return message

    async def retained(self, *names: str) -> dict[str, aiomqtt.Message]:
        """The retained messages of these topics, which a new subscriber gets first."""
        found: dict[str, aiomqtt.Message] = {}
        async with asyncio.timeout(WAIT):
            while set(names) - set(found):
                message = await self.messages.get()
                if message.retain and str(message.topic) in names:
                    found[str(message.topic)] = message
        return found

    async def state(self, topic: str, check: Callable[[Any], bool] = lambda _: True) -> Any:
        """The payload (JSON-decoded when it is JSON) of the next message on `topic` that
        `check` accepts."""

        def wanted(message: aiomqtt.Message) -> bool:
            return str(message.topic) == topic and check(decoded(message))

        return decoded(await self.next(wanted))

    async def send(
        self,
        topic: str,
        params: Any,
        correlation: bytes = b"c1",
        caller: str = "tester",
        *,
        reply_to: str | None = None,
        request_id: str | None = None,
        sent_at: float | None = None,
        retain: bool = False,
        user: list[tuple[str, str]] | None = None,
    ) -> str:
        """Publish an MQTT 5 request as a caller would (its id and time, a response topic
        under the prefix, correlation data); returns the response topic, subscribed."""
        prefix = topic.rsplit("/", 3)[0]
        if reply_to is None:
            reply_to = f"{prefix}/replies/{os.getpid()}/{correlation.decode()}"
        if not set(reply_to) & set("+#"):
            await self.client.subscribe(reply_to, qos=1)
        properties = Properties(PacketTypes.PUBLISH)  # type: ignore[no-untyped-call]
        properties.ResponseTopic = reply_to
        properties.CorrelationData = correlation
        pairs = (
            user
            if user is not None
            else [
                ("client_id", caller),
                ("request_id", request_id or f"{caller}-{next(REQUEST_IDS)}"),
                ("sent_at", f"{time.time() if sent_at is None else sent_at:.3f}"),
            ]
        )
        properties.UserProperty = pairs
        payload = params if isinstance(params, bytes) else json.dumps(params).encode()
        await self.client.publish(topic, payload, qos=1, properties=properties, retain=retain)
        return reply_to

    async def request(
        self,
        topic: str,
        params: Any,
        correlation: bytes = b"c1",
        caller: str = "tester",
        **how: Any,
    ) -> dict[str, Any]:
        """An MQTT 5 request with a response topic and correlation data; its reply."""
        reply_to = await self.send(topic, params, correlation, caller, **how)
        reply = await self.next(lambda m: str(m.topic) == reply_to)
        assert getattr(reply.properties, "CorrelationData", None) == correlation
        answer: dict[str, Any] = decoded(reply)
        return answer

    async def close(self) -> None:
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
            await self._task


def decoded(message: aiomqtt.Message) -> Any:
    payload = message.payload
    assert isinstance(payload, bytes)
    try:
        return json.loads(payload)
    except ValueError:
        return payload.decode()


@contextlib.asynccontextmanager
async def watching(broker: Broker, topic_filter: str) -> AsyncIterator[Watcher]:
    """A fresh subscriber: retained messages first, then live ones, each with the retain
    flag it was published with."""
    client = aiomqtt.Client(
        "127.0.0.1", broker.port, protocol=aiomqtt.ProtocolVersion.V5, timeout=WAIT
    )
    async with client:
        # Retain as published: a retained message keeps its flag even when it arrives live.
        options = SubscribeOptions(qos=1, retainAsPublished=True)
        await client.subscribe(topic_filter, options=options)
        watcher = Watcher(client)
        try:
            yield watcher
        finally:
            await watcher.close()


@dataclass
class Bridged:
    running: Running
    bridge: MqttBridge
    prefix: str


@contextlib.asynccontextmanager
async def bridged(
    tmp_path: Path,
    broker: Broker,
    prefix: str = "test/h1",
    wall: Callable[[], float] = time.time,
    clock: Callable[[], float] = time.monotonic,
    **mqtt: Any,
) -> AsyncIterator[Bridged]:
    """A daemon (tests/daemon/conftest.py) with its MQTT bridge, wired as service.py wires it;
    `wall` the bridge's clock for a command's `sent_at`, `clock` its clock for the command
    rate (and the status interval)."""
    settings: dict[str, Any] = {
        "url": broker.url,
        "topic_prefix": prefix,
        "client_id": f"hostd-{prefix.replace('/', '-')}",
        "status_interval": 0.1,
        "reconnect_min": 0.05,
        "reconnect_max": 0.2,
        **mqtt,
    }
    config = MqttConfig.model_validate(settings)
    async with running_daemon(tmp_path) as running:
        methods = build_methods(running.api)
        bridge = MqttBridge(config, running.api, methods, wall=wall, clock=clock)
        bridge.attach()
        await bridge.load_last_jobs()
        task = asyncio.create_task(bridge.run())
        try:
            yield Bridged(running, bridge, prefix)
        finally:
            await bridge.close(task)


def program(lines: int, step: float = 0.1) -> str:
    """Moves of `step` mm back and forth at 50 mm/s: the simulated board (ten times as
    fast as a real one) takes about step/500 s for each."""
    return "".join(f"G1 X{(i % 2) * step:.3f} F3000\n" for i in range(lines))


# MQTT control packet types (the high nibble of a packet's first byte).
PUBACK = 4


class Packets:
    """Counts the MQTT packets of one type in a byte stream as it passes, in linear time:
    only the fixed header (type, remaining length) of each packet is read."""

    def __init__(self, kind: int) -> None:
        self.kind = kind
        self.count = 0
        self._pending = bytearray()

    def feed(self, data: bytes) -> list[int]:
        """Where, in `data`, each packet of the kind that it completes ends."""
        buf = self._pending
        before = len(buf)
        buf += data
        at = 0
        ends: list[int] = []
        while (packet := self._packet(buf, at)) is not None:
            if buf[at] >> 4 == self.kind:
                self.count += 1
                ends.append(packet - before)
            at = packet
        del buf[:at]
        return ends

    @staticmethod
    def _packet(buf: bytearray, at: int) -> int | None:
        """Where the packet starting at `at` ends, or None: not all of it is here yet."""
        length, header = 0, at + 1
        for shift in (0, 7, 14, 21):  # the remaining length: 1 to 4 bytes
            if header >= len(buf):
                return None
            byte = buf[header]
            header += 1
            length |= (byte & 0x7F) << shift
            if not byte & 0x80:
                end = header + length
                return end if end <= len(buf) else None
        raise AssertionError("a remaining length over 4 bytes: not MQTT")


@dataclass
class Cable:
    """A TCP hop from the bridge to the broker that a test can pull and plug back, while the
    broker runs on: `unplug()` drops the bridge's connection and refuses new ones (the
    broker sees its client vanish, as at a network fault); `plug()` lets it reconnect.

    `cut_after_pubacks` pulls it by itself once that many PUBACKs (the bridge acknowledging
    commands) have passed on to the broker: the broker has them, and the bridge has what
    else it had read. `lose_puback` pulls it just before the broker would have that PUBACK
    (the n-th passed on, counted as `pubacks`): the broker never gets it, nor what follows."""

    upstream: int  # the broker's port
    port: int = field(default_factory=free_port)
    cut_after_pubacks: int | None = None
    lose_puback: int | None = None
    pubacks: int = 0  # PUBACKs passed on, on every connection
    connections: int = 0  # connections passed on
    cut: asyncio.Event = field(default_factory=asyncio.Event)
    _server: asyncio.Server | None = None
    _open: set[asyncio.StreamWriter] = field(default_factory=set)
    _pipes: set[asyncio.Task[None]] = field(default_factory=set)

    @property
    def url(self) -> str:
        return f"mqtt://127.0.0.1:{self.port}"

    async def plug(self) -> None:
        assert self._server is None
        self.cut.clear()
        self._server = await asyncio.start_server(
            self._connect, "127.0.0.1", self.port, reuse_address=True
        )

    async def unplug(self) -> None:
        """Refuse new connections (ECONNREFUSED) and drop the open ones, both sides."""
        if self._server is not None:
            self._server.close()
            self._server = None
        for writer in list(self._open):
            writer.transport.abort()
        self._open.clear()
        self.cut.set()

    async def close(self) -> None:
        await self.unplug()
        for pipe in list(self._pipes):
            pipe.cancel()
        await asyncio.gather(*self._pipes, return_exceptions=True)

    async def _connect(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self._server is None:  # unplugged as this one came in
            writer.transport.abort()
            return
        up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.upstream)
        if self._server is None:  # unplugged while it connected on
            writer.transport.abort()
            up_writer.transport.abort()
            return
        self.connections += 1
        self._open |= {writer, up_writer}
        acks = Packets(PUBACK)
        for pipe in (self._pipe(reader, up_writer, acks), self._pipe(up_reader, writer, None)):
            task = asyncio.create_task(pipe)
            self._pipes.add(task)
            task.add_done_callback(self._pipes.discard)

    async def _pipe(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, acks: Packets | None
    ) -> None:
        with contextlib.suppress(ConnectionError):
            while data := await reader.read(1 << 16):
                if writer not in self._open:
                    return  # unplugged: what comes after is lost, as on a dead network
                ends = [] if acks is None else acks.feed(data)
                lost = self.lose_puback
                if lost is not None and self.pubacks < lost <= self.pubacks + len(ends):
                    # Passed on short of the lost PUBACK's last byte: never a whole packet.
                    writer.write(data[: ends[lost - self.pubacks - 1] - 1])
                    await writer.drain()
                    self.pubacks, self.lose_puback = lost - 1, None
                    await self.unplug()
                    return
                writer.write(data)
                await writer.drain()
                if acks is None:
                    continue
                self.pubacks += len(ends)
                limit = self.cut_after_pubacks
                if limit is not None and self.pubacks >= limit:
                    self.cut_after_pubacks = None
                    await self.unplug()
                    return
        if writer in self._open:  # one side closed: close the other, as TCP would
            writer.close()


@contextlib.asynccontextmanager
async def cable(broker: Broker) -> AsyncIterator[Cable]:
    """A `Cable` to `broker`, plugged in."""
    hop = Cable(broker.port)
    await hop.plug()
    try:
        yield hop
    finally:
        await hop.close()
