"""file.*: the jobs directory: upload, list, delete and analyze.

`file.upload` takes `final`, `upload` and `offset` besides api.md's own
(docs/api.md): chunks stay in their own staging until the final one, and a
retry is idempotent, so a half-uploaded or mixed program is never started; a
full disk or the jobs quota is error 1009. api.md's own chunks (`append:
true` alone) continue what the same connection published (appends.py).
"""

from __future__ import annotations

import asyncio
import contextlib
from typing import TYPE_CHECKING, Annotated, Any, Final, Literal

import structlog
from pydantic import Field

from hostd.api.appends import Chain
from hostd.api.client import Client, current_client
from hostd.api.files import InvalidData, NoSuchFileError, decode
from hostd.api.methods.params import JobFile, MachineId, Params
from hostd.api.rpc import Methods, RpcError
from hostd.api.uploads import ChunkError, NoSuchUpload, StorageError
from hostd.machine.preflight import analyze_for

if TYPE_CHECKING:
    from hostd.api.methods.base import Api

log = structlog.get_logger(__name__)

STORAGE: Final = 1009  # docs/api.md: the jobs directory is full, over its quota, or failing
UploadId = Annotated[str, Field(pattern=r"^[0-9a-f]{32}$")]


class FileName(Params):
    name: JobFile


class UploadParams(FileName):
    data: str
    encoding: Literal["utf-8", "base64"] = "utf-8"
    # Strict, as every other flag of the API: "false" or 0 is -32602, not read as false.
    append: Annotated[bool, Field(strict=True)] = False
    final: Annotated[bool, Field(strict=True)] = True
    upload: UploadId | None = None  # from the first chunk's answer; continues that upload
    # Where this chunk's bytes start: a JSON integer (strict: not "6", 6.0 nor true).
    offset: Annotated[int, Field(strict=True, ge=0)] | None = None


class FileAnalyzeParams(Params):
    file: JobFile
    machine: MachineId | None = None  # its dialect, speeds and travel; none: default rules


class FileMethods:
    def __init__(self, api: Api) -> None:
        self.api = api

    async def file_upload(self, p: UploadParams) -> dict[str, Any]:
        chain = self._chain()
        async with chain.lock if chain is not None else contextlib.nullcontext():
            return await self._upload(p, chain)

    def _chain(self) -> Chain | None:
        """The calling connection's uploads (appends.py); None without a connection (MQTT)."""
        try:
            client: Client = current_client()
        except LookupError:
            return None
        return self.api.appends.of(client)

    async def _upload(self, p: UploadParams, chain: Chain | None) -> dict[str, Any]:
        by_name = p.append and p.upload is None and p.offset is None  # api.md's own chunks
        try:
            data = decode(p.data, p.encoding)
            done = await asyncio.to_thread(
                self.api.jobs.upload,
                p.name,
                data,
                append=p.append,
                final=p.final,
                upload_id=p.upload,
                offset=p.offset,
                by_name=by_name,
                after=chain.last(p.name) if by_name and chain is not None else None,
            )
        except InvalidData as exc:
            raise RpcError(-32602, str(exc)) from None
        except ChunkError as exc:
            raise RpcError(-32602, str(exc), {"expected_offset": exc.expected}) from None
        except NoSuchUpload as exc:
            raise RpcError(1004, str(exc)) from None
        except StorageError as exc:
            log.warning("upload refused", file=p.name, reason=exc.reason, error=exc.message)
            raise RpcError(STORAGE, exc.message, {"reason": exc.reason}) from None
        if chain is not None and done.version is not None:
            chain.published(done.name, done.version)
        result: dict[str, Any] = {"name": done.name, "size": done.size}
        if done.upload is not None:
            result["upload"] = done.upload
        return result

    async def file_list(self) -> list[dict[str, Any]]:
        files = await asyncio.to_thread(self.api.jobs.entries)
        return [{"name": f.name, "size": f.size, "modified": f.modified} for f in files]

    async def file_delete(self, p: FileName) -> dict[str, Any]:
        try:
            await asyncio.to_thread(self.api.jobs.delete, p.name)
        except NoSuchFileError as exc:
            raise RpcError(1004, str(exc)) from None
        return {}

    async def file_analyze(self, p: FileAnalyzeParams) -> dict[str, Any]:
        path = await self.api.resolve(p.file)
        machine = None if p.machine is None else self.api.machine(p.machine)
        return (await analyze_for(machine, path, pool=self.api.daemon.workers)).to_json()


def register(m: Methods, api: Api) -> None:
    h = FileMethods(api)
    m.register("file.upload", UploadParams, h.file_upload)
    m.register("file.list", None, h.file_list)
    m.register("file.delete", FileName, h.file_delete)
    m.register("file.analyze", FileAnalyzeParams, h.file_analyze)
