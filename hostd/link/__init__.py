"""Serial links: device paths in, lines and a typed loss event out."""

from hostd.link.link import Channel, LineReceived, Link, LinkEvent, LinkLost
from hostd.link.serial import BOOTLOADER_BAUD, LinkError

__all__ = [
    "BOOTLOADER_BAUD",
    "Channel",
    "LineReceived",
    "Link",
    "LinkError",
    "LinkEvent",
    "LinkLost",
]
