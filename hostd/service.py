"""`hostd serve`: the daemon in the foreground, as systemd runs it.

Start-up: the config is validated whole (a bad one is one message naming
the file, the key and the problem, and exit status 2), then the socket path
is checked (hostd/api/socketfile.py: a directory others could write, a
planted symlink, a file, a live daemon's socket), then the machines are
built (the soft descriptor limit raised to the hard one first, and the web
server's connections kept within what is left past a reserve for the Unix
socket, the ports and SQLite), then the socket listens, then systemd is
told READY=1. A start-up
failure is one line on stderr and exit status 1, never a traceback. SIGTERM
or SIGINT: STOPPING=1, the socket stops accepting, every running job ends
`interrupted` with its counts written, the ports are closed, the socket
file is removed, exit 0.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import resource
import signal
import sys
from typing import TYPE_CHECKING

import structlog

from hostd.api import socketfile
from hostd.api.methods import Api, build_methods
from hostd.api.mqtt.bridge import MqttBridge
from hostd.api.mqtt.config import read_password
from hostd.api.peer import AccessPolicy, group_id
from hostd.api.rpc import Methods
from hostd.api.server import ApiServer
from hostd.api.socketfile import SocketPathError
from hostd.api.tokens import TokenStore
from hostd.config import Config, ConfigError, load_config

if TYPE_CHECKING:
    from hostd.api.web import WebServer
from hostd.daemon import Daemon
from hostd.logs import configure_logging
from hostd.machine.events import Event, SupervisorChanged
from hostd.notify import Notifier

log = structlog.get_logger(__name__)

# Descriptors the daemon keeps beyond its clients and ports (SQLite and its journal, the
# MQTT connection, the event loop, logging, systemd's notify socket, threads' files).
RESERVE_BASE = 64
# The soft limit set when the hard one is unlimited.
DESCRIPTOR_CEILING = 65536


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", required=True, help="the TOML config file")
    parser.add_argument("--socket", help="the API socket path (overrides [daemon] socket)")
    parser.add_argument("--log-format", choices=("console", "json"), default="console")
    parser.add_argument("--log-level", choices=("debug", "info", "warning", "error"))


def serve_main(args: argparse.Namespace) -> int:
    try:
        config = load_config(args.config)
        policy, gid = _access(config)
        password = _mqtt_password(config)
    except ConfigError as exc:
        print(f"hostd: {exc}", file=sys.stderr)
        return 2
    socket_path = args.socket or config.daemon.socket
    try:
        # Before anything is built: a bad path is one line now, not after the machines.
        socketfile.check_path(socket_path)
    except SocketPathError as exc:
        print(f"hostd: {exc}", file=sys.stderr)
        return 1
    configure_logging(args.log_level or config.daemon.log_level, args.log_format)
    try:
        run = serve(config, socket_path, policy, gid, password)
        if config.daemon.event_loop == "uvloop":
            import uvloop  # a dependency; imported only when chosen

            uvloop.run(run)
        else:
            asyncio.run(run)
    except Exception as exc:
        failure = _start_up_failure(exc)
        if failure is None:
            raise  # a bug: its traceback is what it needs
        print(f"hostd: {failure}", file=sys.stderr)
        return 1
    return 0


def _start_up_failure(exc: BaseException) -> Exception | None:
    """The operator's problem inside `exc` (the path, the system), or None for a bug.

    The socket starts listening inside the daemon's task group, so a failure
    there (the path taken between the check and the bind) arrives wrapped in
    an ExceptionGroup; the operator needs its one line, not the group.
    """
    if isinstance(exc, SocketPathError | OSError):
        return exc
    if isinstance(exc, BaseExceptionGroup) and len(exc.exceptions) == 1:
        return _start_up_failure(exc.exceptions[0])
    return None


def _mqtt_password(config: Config) -> str | None:
    if config.mqtt is None:
        return None
    try:
        return read_password(config.mqtt)
    except OSError as exc:
        where = config.mqtt.password_file
        raise ConfigError(f"[mqtt] password_file: cannot read {where}: {exc.strerror}") from None


def _access(config: Config) -> tuple[AccessPolicy, int | None]:
    group = config.daemon.group
    if group is None:
        return AccessPolicy.default(), None
    try:
        return AccessPolicy.default(group), group_id(group)
    except (KeyError, ValueError):
        raise ConfigError(f"[daemon] group: no group named {group!r}") from None


async def serve(
    config: Config,
    socket_path: str,
    policy: AccessPolicy,
    gid: int | None,
    mqtt_password: str | None = None,
) -> None:
    notifier = Notifier()
    daemon = Daemon(config)
    api = Api(daemon)
    methods = build_methods(api)
    server = ApiServer(
        methods,
        policy=policy,
        socket_gid=gid,
        max_clients=config.daemon.max_clients,
        line_timeout=config.daemon.line_timeout,
    )
    descriptors = raise_descriptor_limit()
    web = _web_server(config, api, methods, descriptors)
    loop = asyncio.get_running_loop()
    bridge = (
        None
        if config.mqtt is None
        else MqttBridge(config.mqtt, api, methods, password=mqtt_password)
    )
    bridge_task: asyncio.Task[None] | None = None

    def stop() -> None:
        log.info("stopping")
        notifier.send(STOPPING=1)
        daemon.stop()

    for signum in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(signum, stop)

    def status(event: Event) -> None:
        if isinstance(event, SupervisorChanged):
            notifier.send(STATUS=_status_line(daemon))

    async def ready() -> None:
        for name in await asyncio.to_thread(api.jobs.clean):
            log.warning("removed an unfinished upload", staging=name)
        api.attach()
        for machine in daemon.machines.values():
            machine.hub.subscribe(status)
        await server.start(socket_path)
        if web is not None:
            await web.start()
        if bridge is not None:
            nonlocal bridge_task
            bridge.attach()
            await bridge.load_last_jobs()
            bridge_task = asyncio.create_task(bridge.run(), name="mqtt")
        # Everything built at start-up lives as long as the daemon: keep it out of
        # the collector's full passes, which otherwise stall the loop (and a `!`)
        # for tens of milliseconds every second or so under load (bench P2f).
        gc.freeze()
        notifier.send(READY=1, STATUS=_status_line(daemon))
        loop = type(asyncio.get_running_loop()).__module__.partition(".")[0]
        log.info("hostd ready", socket=socket_path, machines=list(daemon.machines), loop=loop)

    # The watchdog's pings and the uploads' sweep live as long as the daemon, in a group
    # that ends only once both have: nothing of the daemon's outlives `serve`.
    async with asyncio.TaskGroup() as background:
        watchdog = background.create_task(notifier.watchdog(), name="watchdog")
        expiry = background.create_task(
            api.expire_uploads(_sweep_interval(config)), name="upload-expiry"
        )
        try:
            await daemon.run(ready)
        finally:
            watchdog.cancel()
            expiry.cancel()
            if web is not None:
                await web.close()
            if bridge is not None and bridge_task is not None:
                await bridge.close(bridge_task)
            await server.close()
            notifier.close()
            for signum in (signal.SIGTERM, signal.SIGINT):
                loop.remove_signal_handler(signum)
    log.info("hostd stopped")


def raise_descriptor_limit() -> int:
    """Raise the soft RLIMIT_NOFILE to the hard one (systemd's default soft limit is 1024,
    its hard one 524288); the soft limit now."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY:
        hard = DESCRIPTOR_CEILING
    if soft != resource.RLIM_INFINITY and soft < hard:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
        except (ValueError, OSError) as exc:
            log.warning("descriptor limit not raised", soft=soft, hard=hard, error=str(exc))
            return soft
        log.info("descriptor limit raised", soft=hard, was=soft)
        return hard
    return soft if soft != resource.RLIM_INFINITY else DESCRIPTOR_CEILING


def descriptor_reserve(config: Config) -> int:
    """Descriptors kept from the web server: the Unix socket's clients (admitted, and as
    many again being admitted), two serial ports and a spare per machine, SQLite, MQTT,
    the event loop and logging (RESERVE_BASE)."""
    return 2 * config.daemon.max_clients + 3 * len(config.machines) + RESERVE_BASE


def _web_server(config: Config, api: Api, methods: Methods, descriptors: int) -> WebServer | None:
    """The dashboard (docs/web.md), only when the config has a `[web]` table."""
    if config.web is None:
        return None
    from hostd.api.web import WebServer  # aiohttp loads only for a daemon that serves the web

    spare = max(descriptors - descriptor_reserve(config), 1)
    if spare < config.web.max_connections:
        log.warning(
            "web connections capped by the descriptor limit",
            max_connections=spare,
            configured=config.web.max_connections,
            limit=descriptors,
            reserve=descriptor_reserve(config),
        )
    tokens = TokenStore(config.daemon.state_dir)
    return WebServer(
        methods,
        api.jobs,
        tokens,
        config.web,
        max_clients=config.daemon.max_clients,
        max_connections=spare,
    )


def _sweep_interval(config: Config) -> float:
    """How often abandoned uploads are looked for: a tenth of their expiry, 1 s to 60 s."""
    return min(max(config.daemon.upload_expiry / 10, 1.0), 60.0)


def _status_line(daemon: Daemon) -> str:
    parts = [f"{m.id} {m.supervisor.state.value}" for m in daemon.machines.values()]
    return ", ".join(parts) or "no machines configured"


if __name__ == "__main__":  # `hostd serve` is the way in; this serves tests and debugging
    _parser = argparse.ArgumentParser(prog="hostd serve")
    add_arguments(_parser)
    sys.exit(serve_main(_parser.parse_args()))
