"""The web server's connections: capped in all and per client address, and given
`header_timeout` for their first request's headers.

Each new connection is admitted by the `ConnectionGuard` before aiohttp sees a
byte of it, so the web server can never take the descriptors the Unix
socket, the serial ports and SQLite need. `GuardedRunner` is aiohttp's
AppRunner with the guard in front.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Any, Final, cast

import structlog
from aiohttp import web
from aiohttp.web_protocol import RequestHandler

from hostd.api.tally import Tally
from hostd.api.web.addresses import IPNetwork, in_networks

log = structlog.get_logger(__name__)

# At most one log line a second about connections refused, with how many (`Tally`).
REFUSAL_LOG_INTERVAL: Final = 1.0


class ConnectionGuard:
    """Counts the server's connections: in all, and per client address.

    Asked by each new connection before aiohttp sees a byte of it; one past a
    cap is closed at once (its descriptor freed), and a line is logged at most
    once a second: the first refusal of a burst in full, then how many more (`Tally`).
    """

    def __init__(
        self,
        total: int,
        per_address: int,
        trusted: list[IPNetwork],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.total = total
        self.per_address = per_address
        self._trusted = trusted
        self._count: dict[str, int] = {}
        self.open = 0
        self.refused = 0
        self._refusals = Tally(log, "web connections refused", REFUSAL_LOG_INTERVAL, clock)

    def admit(self, address: str) -> bool:
        over = None
        if self.open >= self.total:
            over = f"{self.total} connections open ([web] max_connections)"
        elif self._count.get(address, 0) >= self.per_address and not in_networks(
            address, self._trusted
        ):
            over = f"{self.per_address} from {address} ([web] max_connections_per_address)"
        if over is not None:
            self.refused += 1
            self._refusals.warning(over=over)
            return False
        self.open += 1
        self._count[address] = self._count.get(address, 0) + 1
        return True

    def flush(self) -> None:
        """Log the refusals still tallied (the server is closing)."""
        self._refusals.flush()

    def release(self, address: str) -> None:
        self.open -= 1
        left = self._count.get(address, 1) - 1
        if left > 0:
            self._count[address] = left
        else:
            self._count.pop(address, None)


class _Handler(RequestHandler):
    """aiohttp's connection, admitted by the guard, and given `header_timeout` for its
    first request's headers (later ones: aiohttp's keep-alive timeout, our `idle_timeout`)."""

    def __init__(
        self, guard: ConnectionGuard, header_timeout: float, *args: Any, **kwargs: Any
    ) -> None:
        super().__init__(*args, **kwargs)
        self._guard = guard
        self._header_timeout = header_timeout
        self._address: str | None = None
        self._header_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        peer = transport.get_extra_info("peername")
        address = str(peer[0]) if isinstance(peer, tuple) and peer else "?"
        if not self._guard.admit(address):
            cast(asyncio.Transport, transport).abort()
            return
        self._address = address
        super().connection_made(transport)
        loop = asyncio.get_running_loop()
        self._header_timer = loop.call_later(self._header_timeout, self._headers_late)

    def _headers_late(self) -> None:
        self._header_timer = None
        log.warning(
            "web connection closed: no request headers in time",
            address=self._address,
            header_timeout=self._header_timeout,
        )
        if self.transport is not None:
            self.transport.abort()

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if self._header_timer is not None and self._request_count:
            self._header_timer.cancel()
            self._header_timer = None

    def connection_lost(self, exc: BaseException | None) -> None:
        if self._address is None:
            return  # never admitted: aiohttp never saw it
        self._guard.release(self._address)
        self._address = None
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None
        super().connection_lost(exc)


class _Server(web.Server):
    """aiohttp's protocol factory, making `_Handler`s."""

    def __init__(self, base: web.Server, guard: ConnectionGuard, header_timeout: float) -> None:
        super().__init__(
            base.request_handler,
            request_factory=base.request_factory,
            handler_cancellation=base.handler_cancellation,
            loop=base._loop,
            **base._kwargs,
        )
        self._guard = guard
        self._header_timeout = header_timeout

    def __call__(self) -> RequestHandler:
        return _Handler(self._guard, self._header_timeout, self, loop=self._loop, **self._kwargs)


class GuardedRunner(web.AppRunner):
    """aiohttp's AppRunner whose connections the guard admits first."""

    def __init__(
        self, app: web.Application, guard: ConnectionGuard, header_timeout: float, **kw: Any
    ) -> None:
        super().__init__(app, **kw)
        self._guard = guard
        self._header_timeout = header_timeout

    async def _make_server(self) -> web.Server:
        return _Server(await super()._make_server(), self._guard, self._header_timeout)

    async def cleanup(self) -> None:
        await super().cleanup()
        self._guard.flush()
