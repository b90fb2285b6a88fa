"""rpc.discover and daemon.info: what this daemon is and what it serves."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from hostd import __version__
from hostd.api import openrpc
from hostd.api.methods.base import API_VERSION
from hostd.api.rpc import Methods

if TYPE_CHECKING:
    from hostd.api.methods.base import Api


class DaemonMethods:
    def __init__(self, api: Api) -> None:
        self.api = api
        self._discovered: dict[str, Any] | None = None

    async def rpc_discover(self) -> dict[str, Any]:
        """This API as an OpenRPC document, made from the method table (hostd/api/openrpc.py)."""
        if self._discovered is None:
            assert self.api.methods is not None, "build_methods has not run"
            self._discovered = openrpc.document(
                self.api.methods, version=__version__, api=API_VERSION
            )
        return self._discovered

    async def daemon_info(self) -> dict[str, Any]:
        machines = list(self.api.daemon.machines)
        return {"version": __version__, "api": API_VERSION, "machines": machines}


def register(m: Methods, api: Api) -> None:
    h = DaemonMethods(api)
    m.register("rpc.discover", None, h.rpc_discover)
    m.register("daemon.info", None, h.daemon_info)
