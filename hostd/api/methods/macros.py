"""macro.*: the config's named G-code snippets, listed and run (hostd/machine/macros.py)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Any

from pydantic import Field

from hostd.api.methods.base import refused
from hostd.api.methods.params import MachineId, MachineParams, Params
from hostd.api.rpc import Methods
from hostd.machine import macros

if TYPE_CHECKING:
    from hostd.api.methods.base import Api

MacroName = Annotated[str, Field(min_length=1, max_length=64)]
ParamName = Annotated[str, Field(min_length=1, max_length=64)]


class MacroListParams(Params):
    machine: MachineId | None = None


class MacroRunParams(MachineParams):
    """`params`: a number per parameter; hostd/machine/macros.py judges each value."""

    name: MacroName
    params: Annotated[dict[ParamName, Any], Field(default_factory=dict, max_length=64)]


class MacroMethods:
    def __init__(self, api: Api) -> None:
        self.api = api

    async def macro_list(self, p: MacroListParams) -> list[dict[str, Any]]:
        if p.machine is not None:
            return macros.listing(self.api.machine(p.machine))
        out: list[dict[str, Any]] = []
        for machine in self.api.daemon.machines.values():
            out += macros.listing(machine)
        return out

    async def macro_run(self, p: MacroRunParams) -> dict[str, Any]:
        machine = self.api.machine(p.machine)
        with refused():
            job = await macros.run(machine, p.name, p.params)
        return {"job": job.id}


def register(m: Methods, api: Api) -> None:
    h = MacroMethods(api)
    m.register("macro.list", MacroListParams, h.macro_list)
    m.register("macro.run", MacroRunParams, h.macro_run)
