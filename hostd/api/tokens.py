"""The web API's access tokens: created by `hostd token create`, kept hashed under state_dir.

A token is 32 random bytes (URL-safe base64, prefixed `hostd_`), shown once
when it is made. The file keeps only its SHA-256: a token has 256 bits of
entropy, so a slow password hash would add nothing, and a leaked file gives
no way in. The file is 0600 and replaced atomically; the daemon re-reads it
when it changes, so a token made or revoked while it runs counts at once.
"""

from __future__ import annotations

import dataclasses
import hashlib
import hmac
import json
import os
import secrets
import time
from pathlib import Path
from typing import Final

TOKENS_FILE: Final = "web-tokens.json"
PREFIX: Final = "hostd_"
MAX_TOKEN: Final = 200  # longer is never a token of ours: refused before hashing


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
        if not token or len(token) > MAX_TOKEN:
            return False
        digest = _digest(token)
        found = False
        for record in self.records():
            found |= hmac.compare_digest(digest, record.sha256)
        return found

    def _write(self, records: list[TokenRecord]) -> None:
        self.path.parent.mkdir(mode=0o750, parents=True, exist_ok=True)
        data = {"tokens": [dataclasses.asdict(r) for r in records]}
        tmp = self.path.with_name(f".{TOKENS_FILE}.{os.getpid()}")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(data, f, indent=1)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self.path)
