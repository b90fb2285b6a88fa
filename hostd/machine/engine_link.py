"""The Engine's link: its lifecycle, from opening to teardown, and reconnecting.

A layer of `Engine` (engine.py). `serve()` owns the connection for the life
of the daemon: it opens the link when asked (`connect`, or at once with
`auto_connect`), runs one connection (`_connection`) until the link is lost
(`link_lost`), the session closes it, or a disconnect is asked (`_end`),
tears it down as one (`_teardown`: the session settles every line and
request the link carried), and reconnects with back-off (RECONNECT_BACKOFF),
at once while a reset reboots the board (`_restarting`), never while the
session gave up a board that may move (`_hold_reopen`). The link's going up
and down is told to the Machine here (`_on_ready`, `_publish_link`).

This layer lies below the delivery loop and the reading, and reaches them
only through two hooks it declares and the layers above implement:
`_deliver` (engine_delivery.py), which runs after the session opens and
closes, and `link_lines` (engine.py), the read callback that `Link.open` is
given with `receiver=self`.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

from hostd.link import Channel, Link, LinkError
from hostd.machine.engine_state import EngineState, LinkState
from hostd.machine.events import LinkChanged
from hostd.protocol.errors import NotConnected

RECONNECT_BACKOFF = (0.1, 0.2, 0.5, 1.0, 2.0, 5.0)


class EngineLink(EngineState):
    """The link's lifecycle (see `Engine`)."""

    # -- hooks: declared here, implemented above ---------------------------

    def _deliver(self) -> None:
        """Hook: the delivery loop, `EngineDelivery._deliver` (engine_delivery.py).

        A connection's opening and its teardown are steps of the session
        (`open`, `close`) whose writes and events it delivers.
        """
        raise NotImplementedError

    def link_lines(self, channel: Channel, lines: list[bytes]) -> None:
        """Hook: the link's read callback, `Engine.link_lines` (engine.py).

        `_connection` gives the engine itself to `Link.open` as its receiver
        (`link_lines`, `link_lost`); the reading is the top layer.
        """
        raise NotImplementedError

    # -- lifecycle -------------------------------------------------------

    async def serve(self) -> None:
        """Own this machine's connection until cancelled."""
        if self.config.auto_connect:
            self._want.set()
        failures = 0
        while True:
            await self._want.wait()
            self._hold_reopen = False
            if not self.config.auto_connect:
                self._want.clear()  # this request is being served; a later one sets it again
            was_ready = await self._connection()
            if self._stop.is_set():  # a disconnect was asked for
                self._stop.clear()
                continue
            failures = 0 if was_ready else failures + 1
            if self._hold_reopen:
                continue  # until connect() asks: `_want` is clear
            if self._restarting():
                # The board is rebooting: its device comes back in a moment.
                self._want.set()
                await asyncio.sleep(RECONNECT_BACKOFF[0])
            elif self._want.is_set():
                await asyncio.sleep(RECONNECT_BACKOFF[min(failures, len(RECONNECT_BACKOFF) - 1)])

    def _restarting(self) -> bool:
        deadline = self._restart_deadline
        if deadline is not None and time.monotonic() >= deadline:
            self._restart_deadline = deadline = None
        return deadline is not None

    async def connect(self) -> None:
        """Open the link and handshake; NotConnected with the reason if that fails."""
        if self.ready:
            return
        failed = self._attempt_failed
        if failed is None or failed.done():
            failed = self._attempt_failed = asyncio.get_running_loop().create_future()
        self._want.set()
        ready = asyncio.ensure_future(self._ready.wait())
        waiting: list[asyncio.Future[Any]] = [ready, failed]
        try:
            await asyncio.wait(waiting, return_when=asyncio.FIRST_COMPLETED)
        finally:
            ready.cancel()
            await asyncio.wait({ready})  # it ends here, not after its asker (never re-raises)
        if not self.ready:
            reason = failed.result() if failed.done() else "not connected"
            raise NotConnected(f"{self.id}: {reason}")

    @property
    def ready(self) -> bool:
        """Clients may use the board (not while a grbl board re-syncs after its reset)."""
        return self.link_state is LinkState.READY and self.session.ready

    async def disconnect(self) -> None:
        self._want.clear()
        if self.link_state is not LinkState.DOWN:
            self._stop.set()
            self._end("disconnected")
            await self._down.wait()

    async def _connection(self) -> bool:
        """One connection, opening to teardown: whether it got ready. Raises only if cancelled."""
        self.link_state = LinkState.OPENING
        self._down.clear()
        config = self.config
        try:
            self.link = await Link.open(
                config.data_port, config.control_port, config.baudrate, receiver=self
            )
        except LinkError as exc:
            self._end_attempt(str(exc))
            self._teardown(str(exc))
            return False
        closed = self._closed = asyncio.get_running_loop().create_future()
        if self._stop.is_set():
            closed.set_result("disconnected")
        reason = "closed"
        try:
            self.link_state = LinkState.HANDSHAKE
            self.session.open(rebooting=self._restart_deadline is not None)
            self._deliver()
            reason = await closed
        finally:
            was_ready = self.link_state is LinkState.READY
            link, self.link = self.link, None
            try:
                await link.close()  # released before anyone hears it is down
            finally:
                self._end_attempt(reason)
                self._teardown(reason)
        return was_ready

    def _end(self, reason: str) -> None:
        """This connection is over: its task tears it down."""
        if self._closed is not None and not self._closed.done():
            self._closed.set_result(reason)

    def _on_ready(self) -> None:
        self._restart_deadline = None
        self.link_state = LinkState.READY
        self._ready.set()
        self._publish_link(True, "ready")
        self._log.info("machine ready", state=self.model.state)

    def _end_attempt(self, reason: str) -> None:
        if self._attempt_failed is not None and not self._attempt_failed.done():
            self._attempt_failed.set_result(reason)

    def _teardown(self, reason: str) -> None:
        """The link is gone: the session settles every line and request it carried."""
        self.link_state = LinkState.DOWN
        self._ready.clear()
        self._closed = None
        self.session.close(reason, restarted=self._restart_deadline is not None)
        self._deliver()
        if self._timer is not None:
            self._timer.cancel()
            self._timer = self._timer_at = None
        self._log.info("link down", reason=reason)
        self._publish_link(False, reason)
        self._down.set()
        self._changed.set()

    def link_lost(self, reason: str) -> None:
        self._end(reason)

    def _publish_link(self, up: bool, reason: str) -> None:
        self._up(LinkChanged(self.id, up, reason))
