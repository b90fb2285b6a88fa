"""api.md's chunked upload, per connection: a first `file.upload`, then `append: true`.

api.md's `file.upload` has no upload id and no offset: a client sends a
first chunk, then the next ones with `append: true`, and after the last
call the file holds every chunk in order. What makes that safe here
(uploads.py publishes; this module remembers, per connection):

- The calls of one connection run one after another, in the order they
  arrived, even when the client pipelines them (`lock`): its chunks can
  never overtake each other.
- Each connection remembers the version (inode, size, write time) of each file it
  last published. An append without `offset` continues that version, and
  only while it is still the one published; another client's upload of the
  same name, a delete, a daemon restart (a new connection remembers
  nothing) make the chunk a clear error instead of a mix.
- What a connection remembers goes with it: its disconnect hook forgets
  it. At most MAX_NAMES names per connection are remembered, the most
  recently uploaded; an append to one forgotten is refused like any other.

A request without a connection (an MQTT command) has no chunks to continue:
its appends without `offset` are refused.
"""

from __future__ import annotations

import asyncio
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Final

from hostd.api.client import Client
from hostd.machine.jobfile import Version

MAX_NAMES: Final = 64  # names one connection is remembered to have published


@dataclass(slots=True)
class Chain:
    """One connection's uploads: one at a time, and what each name last became."""

    lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    versions: OrderedDict[str, Version] = field(default_factory=OrderedDict)

    def last(self, name: str) -> Version | None:
        """The version of `name` this connection last published, if it is remembered."""
        return self.versions.get(name)

    def published(self, name: str, version: Version) -> None:
        self.versions[name] = version
        self.versions.move_to_end(name)
        while len(self.versions) > MAX_NAMES:
            self.versions.popitem(last=False)


class Appends:
    """The chains of the connected clients; each is forgotten when its client leaves."""

    def __init__(self) -> None:
        self._chains: dict[Client, Chain] = {}  # by identity: a Client defines no __eq__

    def of(self, client: Client) -> Chain:
        chain = self._chains.get(client)
        if chain is None:
            chain = self._chains[client] = Chain()
            client.on_disconnect.append(lambda: self._chains.pop(client, None))
        return chain

    def __len__(self) -> int:
        return len(self._chains)
