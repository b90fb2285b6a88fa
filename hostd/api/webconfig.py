"""The dashboard's section of the config file, `[web]` (docs/web.md): its HTTP server."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, IPvAnyNetwork, field_validator


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class WebConfig(_Strict):
    """The dashboard's HTTP server (hostd/api/web/); docs/web.md."""

    # "host:port", "[v6 address]:port"; port 0 picks a free one (tests).
    listen: str
    # False: watch only; the methods that move or change anything are refused.
    control: bool = True
    # Login attempts one address may make a minute (successful ones count too).
    login_attempts: Annotated[int, Field(ge=1, le=1000)] = 5
    # Further names the dashboard answers to (a LAN name, a reverse proxy's): requests
    # naming any other host are refused, against DNS rebinding. IP addresses,
    # `localhost` and the `listen` host always do.
    hosts: list[Annotated[str, Field(min_length=1, max_length=253)]] = []
    # Reverse proxies (addresses or networks) whose X-Forwarded-For and X-Forwarded-Proto
    # are believed: the client address (logs, login limit, connection caps) is then the
    # last one in X-Forwarded-For that is not a trusted proxy. Nobody else's are.
    trusted_proxies: list[IPvAnyNetwork] = []
    # Seconds a new connection has to send its first request's headers; seconds an
    # idle connection (between requests, or an upload's body that stops) stays open.
    header_timeout: Annotated[float, Field(gt=0, le=600)] = 10.0
    idle_timeout: Annotated[float, Field(gt=0, le=3600)] = 60.0
    # Connections (HTTP and WebSocket) at once, in all and from one client address
    # (a trusted proxy counts in the total only). The total is also kept within the
    # descriptors the daemon can spare (docs/web.md).
    max_connections: Annotated[int, Field(ge=1, le=100_000)] = 256
    max_connections_per_address: Annotated[int, Field(ge=1, le=100_000)] = 32
    # Seconds a login session may go unused before it ends.
    session_expiry: Annotated[float, Field(gt=0)] = 7 * 86400.0

    @field_validator("listen")
    @classmethod
    def _host_and_port(cls, listen: str) -> str:
        split_listen(listen)
        return listen

    @property
    def host(self) -> str:
        return split_listen(self.listen)[0]

    @property
    def port(self) -> int:
        return split_listen(self.listen)[1]


def split_listen(listen: str) -> tuple[str, int]:
    """("127.0.0.1", 7080) from "127.0.0.1:7080", ("::1", 7080) from "[::1]:7080"."""
    host, sep, port = listen.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not sep or not host or not port.isdigit() or int(port) > 65535:
        raise ValueError(f"{listen!r}: expected host:port, e.g. 127.0.0.1:7080")
    return host, int(port)
