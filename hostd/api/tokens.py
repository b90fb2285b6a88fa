"""The web API's access tokens: created by `hostd token create`, kept hashed under state_dir.

A token is 32 random bytes (URL-safe base64, prefixed `hostd_`), shown once
when it is made. The file keeps only its SHA-256: a token has 256 bits of
entropy, so a slow password hash would add nothing, and a leaked file gives
no way in. The file is replaced atomically; the daemon re-reads it when it
changes, so a token made or revoked while it runs counts at once.

Who may read it: the daemon, whoever wrote it. `sudo hostd token create`
runs as root, the service as `hostd`: a root-only file would make every
login fail. So the file is 0640 and takes the owner and group of the
directory it is in (the state directory, which systemd's `StateDirectory=`
gives to the service's user and group).

A browser does not keep the token: `POST /login` trades it for a session
(`Sessions`), a random id held in memory and tied to the token's id, so a
stolen cookie is no token, and revoking the token ends its sessions.
"""

from __future__ import annotations

import dataclasses
import hashlib
import hmac
import json
import os
import secrets
import time
from collections.abc import Callable
from pathlib import Path
from typing import Final

TOKENS_FILE: Final = "web-tokens.json"
PREFIX: Final = "hostd_"
MAX_TOKEN: Final = 200  # longer is never a token of ours: refused before hashing
FILE_MODE: Final = 0o640  # the service's user writes and reads, its group reads
# Sessions at once (a browser each); past it the least recently used is forgotten.
MAX_SESSIONS: Final = 1000


@dataclasses.dataclass(frozen=True, slots=True)
class TokenRecord:
    id: str  # the hash's first 12 hex digits: names a token without revealing it
    name: str
    created: float
    sha256: str


def _digest(token: str) -> str:
    return hashlib.sha256(token.encode("utf-8", "surrogatepass")).hexdigest()


class TokenStore:
    def __init__(self, state_dir: str | os.PathLike[str]) -> None:
        self.path = Path(state_dir) / TOKENS_FILE
        self._seen: tuple[int, int] | None = None  # (mtime_ns, size) of what _records holds
        self._records: list[TokenRecord] = []

    def create(self, name: str = "") -> str:
        """A new token; only its hash is written. Returns the token, to be shown once."""
        token = PREFIX + secrets.token_urlsafe(32)
        digest = _digest(token)
        record = TokenRecord(digest[:12], name, time.time(), digest)
        self._write([*self.records(), record])
        return token

    def revoke(self, token_id: str) -> bool:
        records = self.records()
        kept = [r for r in records if r.id != token_id]
        if len(kept) == len(records):
            return False
        self._write(kept)
        return True

    def records(self) -> list[TokenRecord]:
        """The tokens on file now (re-read only when the file changed)."""
        try:
            st = self.path.stat()
        except FileNotFoundError:
            self._seen, self._records = None, []
            return []
        seen = (st.st_mtime_ns, st.st_size)
        if seen != self._seen:
            data = json.loads(self.path.read_text(encoding="utf-8"))
            self._records = [TokenRecord(**entry) for entry in data["tokens"]]
            self._seen = seen
        return list(self._records)

    def verify(self, token: str | None) -> bool:
        """Whether `token` is one on file; compared in constant time against each."""
        return self.identify(token) is not None

    def identify(self, token: str | None) -> str | None:
        """The id of the record `token` is, or None; compared in constant time against each."""
        if not token or len(token) > MAX_TOKEN:
            return None
        digest = _digest(token)
        found = None
        for record in self.records():
            if hmac.compare_digest(digest, record.sha256):
                found = record.id
        return found

    def ids(self) -> set[str]:
        return {record.id for record in self.records()}

    def _write(self, records: list[TokenRecord]) -> None:
        self.path.parent.mkdir(mode=0o750, parents=True, exist_ok=True)
        data = {"tokens": [dataclasses.asdict(r) for r in records]}
        tmp = self.path.with_name(f".{TOKENS_FILE}.{os.getpid()}")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, FILE_MODE)
        directory = os.stat(self.path.parent)
        if os.geteuid() == 0:  # root writing for the service: the directory's owner reads it
            os.fchown(fd, directory.st_uid, directory.st_gid)
        os.fchmod(fd, FILE_MODE)  # whatever the umask
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(data, f, indent=1)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self.path)


@dataclasses.dataclass(slots=True)
class _Session:
    token_id: str
    used: float


class Sessions:
    """Browser sessions: a random id (the cookie) for a token id, in memory only.

    Only the id's SHA-256 is kept, so even the daemon's memory holds no cookie.
    A session unused for `expiry` seconds is gone; a restart ends them all (the
    browser logs in again). At most MAX_SESSIONS: the least recently used goes.
    """

    def __init__(self, expiry: float, clock: Callable[[], float] = time.monotonic) -> None:
        self._expiry = expiry
        self._clock = clock
        self._by_digest: dict[str, _Session] = {}  # in order of last use

    def __len__(self) -> int:
        return len(self._by_digest)

    def create(self, token_id: str) -> str:
        session_id = secrets.token_urlsafe(32)
        self._by_digest[_digest(session_id)] = _Session(token_id, self._clock())
        while len(self._by_digest) > MAX_SESSIONS:
            del self._by_digest[next(iter(self._by_digest))]
        return session_id

    def token_id(self, session_id: str | None) -> str | None:
        """The token a live session stands for (and it counts as used now), or None."""
        if not session_id or len(session_id) > MAX_TOKEN:
            return None
        key = _digest(session_id)
        session = self._by_digest.pop(key, None)
        if session is None:
            return None
        now = self._clock()
        if now - session.used > self._expiry:
            return None
        session.used = now
        self._by_digest[key] = session  # most recently used last
        return session.token_id

    def end(self, session_id: str | None) -> None:
        if session_id:
            self._by_digest.pop(_digest(session_id), None)

    def keep_only(self, token_ids: set[str]) -> int:
        """Drop the sessions of tokens no longer on file; how many went."""
        gone = [k for k, s in self._by_digest.items() if s.token_id not in token_ids]
        for key in gone:
            del self._by_digest[key]
        return len(gone)
