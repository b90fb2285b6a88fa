"""fault.*: the machine's fault table, its overrides and clears."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Any

from pydantic import Field

from hostd.api.methods.params import MachineParams
from hostd.api.rpc import Methods

if TYPE_CHECKING:
    from hostd.api.methods.base import Api


class FaultParams(MachineParams):
    fault: str


class FaultOverrideParams(FaultParams):
    override: Annotated[bool, Field(strict=True)]  # "false" or 0 is -32602, not false


class FaultMethods:
    def __init__(self, api: Api) -> None:
        self.api = api

    async def fault_list(self, p: MachineParams) -> list[dict[str, Any]]:
        return [f.to_json() for f in self.api.machine(p.machine).faults.all()]

    async def fault_override(self, p: FaultOverrideParams) -> dict[str, Any]:
        return self.api.machine(p.machine).override_fault(p.fault, p.override).to_json()

    async def fault_clear(self, p: FaultParams) -> dict[str, Any]:
        return self.api.machine(p.machine).clear_fault(p.fault).to_json()


def register(m: Methods, api: Api) -> None:
    h = FaultMethods(api)
    m.register("fault.list", MachineParams, h.fault_list)
    m.register("fault.override", FaultOverrideParams, h.fault_override)
    m.register("fault.clear", FaultParams, h.fault_clear)
