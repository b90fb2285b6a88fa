"""The link's keys of a machine's table: its ports and their speed (running.md)."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, field_validator

from hostd.link.serial import BOOTLOADER_BAUD


class PortConfig(BaseModel):
    """Where the board is: `data_port`, the optional `control_port`, `baudrate`."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    data_port: Annotated[str, Field(min_length=1)]
    control_port: str | None = None
    baudrate: Annotated[int, Field(gt=0)] = 115200

    @field_validator("baudrate")
    @classmethod
    def _not_the_bootloader_touch(cls, v: int) -> int:
        if v == BOOTLOADER_BAUD:
            raise ValueError(f"{BOOTLOADER_BAUD} baud resets the board into its bootloader")
        return v
