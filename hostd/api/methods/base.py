"""The context every topic's methods share: the daemon, its jobs directory, its clients.

`Api` holds what is common (the machine look-up, the job store, the jobs
directory, the subscriptions) and no method; each topic module (machine.py,
files.py, jobs.py, faults.py, settings.py, subscriptions.py, daemon.py)
registers its own methods onto it (hostd/api/methods/__init__.py).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable, Iterator
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import structlog

from hostd.api.appends import Appends
from hostd.api.files import JobsDir, NoSuchFileError
from hostd.api.methods.subscriptions import JOB_LINES, STATUS_LINES, Subscriptions, publish
from hostd.api.rpc import RpcError
from hostd.daemon import Daemon
from hostd.machine.machine import Machine
from hostd.protocol.commands import InvalidCommand

if TYPE_CHECKING:
    from hostd.api.rpc import Methods

log = structlog.get_logger(__name__)

API_VERSION = 1


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

    def _console_interest(self) -> None:
        """Engines publish their raw traffic only while someone listens to it."""
        for machine in self.daemon.machines.values():
            # Every line for a subscription that keeps a job's lines (api.md's default);
            # all but those for one that asked `job_lines: false`.
            machine.console = self.subscriptions.wants(JOB_LINES, machine.id)
            machine.console_but_job = self.subscriptions.wants("console", machine.id)
            # Status polls and reports for a subscription that did not ask to leave them out.
            machine.console_status = self.subscriptions.wants(STATUS_LINES, machine.id)

    def attach(self) -> None:
        """Listen to every machine (call once the daemon has built them)."""
        for machine in self.daemon.machines.values():
            machine.hub.subscribe(partial(publish, self.subscriptions, machine))

    def machine(self, machine_id: str) -> Machine:
        """The machine of that id, or 1001."""
        machine = self.daemon.machine(machine_id)
        if machine is None:
            raise RpcError(1001, f"unknown machine {machine_id!r}")
        return machine

    async def store(self) -> Any:
        """The job store, or -32603 while it is not open."""
        store = self.daemon.store
        if store is None:
            raise RpcError(-32603, "the job store is not open")
        return store

    async def resolve(self, name: str) -> Path:
        """A file of the jobs directory, or 1004."""
        try:
            return await asyncio.to_thread(self.jobs.resolve, name)
        except NoSuchFileError as exc:
            raise RpcError(1004, str(exc)) from None

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


@contextlib.contextmanager
def refused() -> Iterator[None]:
    """A line the machine refuses (InvalidCommand) is -32602, as in machine.send."""
    try:
        yield
    except InvalidCommand as exc:
        raise RpcError(-32602, exc.message, exc.data) from None
