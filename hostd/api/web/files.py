"""`/files/<name>`: a program up into the jobs directory, and down for the page's preview.

An upload's body is streamed into staging a chunk at a time through the same
staging, name rules and quota as `file.upload` (uploads.py), and published
when it ends; one cut off or refused leaves nothing behind. Uploads refuse
another site's `Origin`, and are off when the web API is watch only.
"""

from __future__ import annotations

import asyncio
import os
from typing import Final

import structlog
from aiohttp import web

from hostd.api.files import FileNameError, JobsDir, check_name
from hostd.api.uploads import NoSuchUpload, StorageError
from hostd.api.web.auth import Auth
from hostd.api.web.responses import error
from hostd.api.webconfig import WebConfig
from hostd.machine.jobfile import NoSuchFile, open_binary

log = structlog.get_logger(__name__)

CHUNK: Final = 1 << 20  # an upload's body goes to staging a MiB at a time


class FileRoutes:
    """The handlers of `GET` and `POST /files/<name>`, on the daemon's own jobs directory."""

    def __init__(self, jobs: JobsDir, config: WebConfig, auth: Auth) -> None:
        self._jobs = jobs
        self._config = config
        self._auth = auth

    async def download(self, request: web.Request) -> web.StreamResponse:
        """A program's text, for the page's preview (the daemon's own jobs directory only).

        The file is opened as `JobsDir.resolve` checks it, on the descriptor
        (jobfile.py: a link or a FIFO swapped in after a check is refused, not
        followed), and what is sent is what was opened.
        """
        try:
            name = check_name(request.match_info["name"])
            file = await asyncio.to_thread(open_binary, self._jobs.path / name)
        except FileNameError as exc:
            return error(400, str(exc))
        except NoSuchFile as exc:
            return error(404, exc.message)
        try:
            response = web.StreamResponse(headers={"Content-Type": "text/plain; charset=utf-8"})
            left = response.content_length = os.fstat(file.fileno()).st_size
            await response.prepare(request)
            while left and (chunk := await asyncio.to_thread(file.read, min(CHUNK, left))):
                await response.write(chunk)
                left -= len(chunk)
            await response.write_eof()
            return response
        finally:
            file.close()

    async def upload(self, request: web.Request) -> web.StreamResponse:
        """The body, streamed into staging a chunk at a time, published when it ends."""
        if self._auth.foreign_origin(request):
            return error(403, "upload from another site refused")
        if not self._config.control:
            return error(403, "uploads are off: the web API is watch only ([web] control = false)")
        try:
            name = check_name(request.match_info["name"])
        except FileNameError as exc:
            return error(400, str(exc))
        upload: str | None = None
        offset = 0
        finished = False
        try:
            while True:
                try:
                    async with asyncio.timeout(self._config.idle_timeout):
                        chunk = await request.content.read(CHUNK)
                except TimeoutError:
                    log.warning("web upload stalled", file=name, received=offset)
                    return error(408, f"no data for {self._config.idle_timeout:g} s")
                if not chunk:
                    break
                done = await asyncio.to_thread(
                    self._jobs.upload, name, chunk, final=False, upload_id=upload, offset=offset
                )
                upload, offset = done.upload, offset + len(chunk)
            done = await asyncio.to_thread(
                self._jobs.upload, name, b"", final=True, upload_id=upload, offset=offset
            )
            finished = True
        except StorageError as exc:
            log.warning("web upload refused", file=name, reason=exc.reason, error=exc.message)
            return error(507, exc.message)
        except NoSuchUpload as exc:  # expired mid-body: only a very slow sender
            return error(408, str(exc))
        finally:
            if not finished:  # failed or cut off (the peer gone): its staging goes now
                await self._abort_upload(name, upload)
        log.info("web upload", file=name, size=done.size)
        return web.json_response({"name": done.name, "size": done.size})

    async def _abort_upload(self, name: str, upload: str | None) -> None:
        if upload is None:
            return
        try:
            await asyncio.shield(asyncio.to_thread(self._jobs.uploads.abort, upload))
        except OSError as exc:
            log.error("web upload staging not removed", file=name, error=str(exc))
        else:
            log.info("web upload failed; staging removed", file=name)
