"""settings.get and settings.set: the board's settings, by the dialect's names."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Any

from pydantic import Field, field_validator

from hostd.api.methods.params import MachineParams
from hostd.api.rpc import Methods
from hostd.protocol.settings import check_key, check_values

if TYPE_CHECKING:
    from hostd.api.methods.base import Api

SettingKey = Annotated[str, Field(min_length=1, max_length=16, pattern=r"^[A-Za-z0-9_]+$")]
SettingValue = bool | int | float | str  # bounded by hostd.protocol.settings.check_values


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


class SettingsMethods:
    def __init__(self, api: Api) -> None:
        self.api = api

    async def settings_get(self, p: SettingsGetParams) -> dict[str, Any]:
        return await self.api.machine(p.machine).read_settings(list(p.keys))

    async def settings_set(self, p: SettingsSetParams) -> dict[str, Any]:
        _, bodies = await self.api.machine(p.machine).write_settings(dict(p.values))
        merged: dict[str, Any] = {}
        for body in bodies:
            merged.update(body)
        return merged or dict(p.values)  # grbl answers a `$N=V` with a bare ok


def register(m: Methods, api: Api) -> None:
    h = SettingsMethods(api)
    m.register("settings.get", SettingsGetParams, h.settings_get)
    m.register("settings.set", SettingsSetParams, h.settings_set)
