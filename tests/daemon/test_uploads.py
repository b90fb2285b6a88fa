"""Uploads through the daemon's socket: never a mixed or partial file, whatever clients do.

A real daemon (simulated machine, jobs directory on disk) and real
connections; what the file system holds is read from the disk itself.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from pathlib import Path
from typing import Any

import pytest

from hostd.api.appends import Chain
from hostd.api.client import Client
from hostd.api.methods import UploadParams
from hostd.api.rpc import RpcError
from tests.daemon.conftest import Rpc, RpcFailure, Running, running_daemon

pytestmark = pytest.mark.asyncio


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


async def fails(code: int, call: Any) -> RpcFailure:
    with pytest.raises(RpcFailure) as err:
        await call
    assert err.value.code == code, err.value
    return err.value


def staged(hostd: Running) -> dict[str, bytes]:
    staging = hostd.jobs / ".staging"
    return {p.name: p.read_bytes() for p in staging.iterdir()} if staging.exists() else {}


async def chunk(rpc: Rpc, name: str, data: str, upload: str, offset: int, final: bool) -> Any:
    return await rpc.call(
        "file.upload", name=name, data=data, upload=upload, offset=offset, final=final
    )


async def test_two_clients_uploading_one_name_each_publish_exactly_their_own_bytes(
    rpc: Rpc, hostd: Running
) -> None:
    other = await hostd.client()
    mine = [f"G1 X{i} (mine)\n" for i in range(3)]
    theirs = [f"G1 Y{i} (theirs, longer)\n" for i in range(3)]
    a, b = await asyncio.gather(
        rpc.call("file.upload", name="part.gcode", data=mine[0], final=False),
        other.call("file.upload", name="part.gcode", data=theirs[0], final=False),
    )
    assert a["upload"] != b["upload"]
    await asyncio.gather(
        chunk(rpc, "part.gcode", mine[1], a["upload"], a["size"], False),
        chunk(other, "part.gcode", theirs[1], b["upload"], b["size"], False),
    )
    assert await rpc.call("file.list") == []
    await fails(1004, rpc.call("job.start", machine="sim1", file="part.gcode"))

    size = len("".join(mine[:2]).encode())
    await chunk(rpc, "part.gcode", mine[2], a["upload"], size, True)
    assert (hostd.jobs / "part.gcode").read_text() == "".join(mine)

    size = len("".join(theirs[:2]).encode())
    await chunk(other, "part.gcode", theirs[2], b["upload"], size, True)
    assert (hostd.jobs / "part.gcode").read_text() == "".join(theirs)
    assert staged(hostd) == {}
    await other.close()


async def test_a_retried_chunk_is_idempotent_and_a_wrong_offset_names_the_right_one(
    rpc: Rpc, hostd: Running
) -> None:
    first = await rpc.call("file.upload", name="a.gcode", data="G0 X1\n", final=False)
    upload = first["upload"]
    second = await chunk(rpc, "a.gcode", "G0 X2\n", upload, 6, False)
    assert await chunk(rpc, "a.gcode", "G0 X2\n", upload, 6, False) == second

    wrong = await fails(-32602, chunk(rpc, "a.gcode", "G0 X3\n", upload, 6, False))
    assert wrong.data == {"expected_offset": 12}
    assert "expected offset 12" in wrong.message
    gap = await fails(-32602, chunk(rpc, "a.gcode", "G0 X3\n", upload, 13, True))
    assert gap.data == {"expected_offset": 12}

    done = await chunk(rpc, "a.gcode", "G0 X3\n", upload, 12, True)
    assert done == {"name": "a.gcode", "size": 18}
    assert await chunk(rpc, "a.gcode", "G0 X3\n", upload, 12, True) == done  # the answer was lost
    assert (hostd.jobs / "a.gcode").read_bytes() == b"G0 X1\nG0 X2\nG0 X3\n"


async def test_api_md_chunks_on_one_connection_give_the_whole_file_in_order(
    rpc: Rpc, hostd: Running
) -> None:
    """A client written from api.md: a first call, then `append: true`, nothing else."""
    chunks = [f"G1 X{i} Y{i * 2}\n" for i in range(8)]
    sent = ""
    for i, text in enumerate(chunks):
        params: dict[str, Any] = {"append": True} if i else {}
        answer = await rpc.call("file.upload", name="part.gcode", data=text, **params)
        sent += text
        assert answer == {"name": "part.gcode", "size": len(sent)}
        # Listed at every step as exactly what was sent so far, never part of a chunk.
        assert (hostd.jobs / "part.gcode").read_text() == sent
    assert await rpc.call("file.list") == [
        {"name": "part.gcode", "size": len(sent), "modified": ANY_TIME}
    ]
    assert staged(hostd) == {}


class _AnyTime:
    def __eq__(self, other: object) -> bool:
        return isinstance(other, str) and other.endswith("Z")


ANY_TIME: Any = _AnyTime()


async def test_api_md_chunks_pipelined_on_one_connection_stay_in_order(
    rpc: Rpc, hostd: Running
) -> None:
    """Requests of one connection run concurrently; its chunks still land in order."""
    chunks = [f"G1 X{i}\n" for i in range(40)]
    requests = [
        {"jsonrpc": "2.0", "id": i + 1, "method": "file.upload",
         "params": {"name": "p.gcode", "data": text, **({"append": True} if i else {})}}
        for i, text in enumerate(chunks)
    ]  # fmt: skip
    waiting = [asyncio.get_running_loop().create_future() for _ in requests]
    rpc._waiting.update({r["id"]: w for r, w in zip(requests, waiting, strict=True)})
    rpc.writer.write(b"".join(json.dumps(r).encode() + b"\n" for r in requests))

    async with asyncio.timeout(15):
        answers = await asyncio.gather(*waiting)

    sizes = [a["result"]["size"] for a in answers]
    assert sizes == [sum(len(c) for c in chunks[: i + 1]) for i in range(len(chunks))]
    assert (hostd.jobs / "p.gcode").read_text() == "".join(chunks)


async def test_api_md_chunks_of_two_clients_on_one_name_never_mix(rpc: Rpc, hostd: Running) -> None:
    other = await hostd.client()
    await rpc.call("file.upload", name="a.gcode", data="G0 X1 (mine)\n")
    await other.call("file.upload", name="a.gcode", data="G0 Y1 (theirs)\n")

    refused = await fails(
        -32602, rpc.call("file.upload", name="a.gcode", data="G0 X2 (mine)\n", append=True)
    )

    assert "replaced by another upload" in refused.message
    assert "nothing was appended" in refused.message
    assert (hostd.jobs / "a.gcode").read_text() == "G0 Y1 (theirs)\n"
    await other.call("file.upload", name="a.gcode", data="G0 Y2 (theirs)\n", append=True)
    assert (hostd.jobs / "a.gcode").read_text() == "G0 Y1 (theirs)\nG0 Y2 (theirs)\n"
    await other.close()


async def test_api_md_chunks_on_a_new_connection_or_after_a_delete_are_refused(
    rpc: Rpc, hostd: Running
) -> None:
    await rpc.call("file.upload", name="a.gcode", data="old\n")
    later = await hostd.client()  # a reconnect: the daemon cannot know it is the same client

    refused = await fails(-32602, later.call("file.upload", name="a.gcode", data="X", append=True))

    assert "it uploaded none" in refused.message and refused.data == {"expected_offset": 4}
    assert (hostd.jobs / "a.gcode").read_bytes() == b"old\n"
    appended = await later.call("file.upload", name="a.gcode", data="G0\n", append=True, offset=4)
    assert appended == {"name": "a.gcode", "size": 7}
    assert (hostd.jobs / "a.gcode").read_bytes() == b"old\nG0\n"
    await later.call("file.delete", name="a.gcode")
    deleted = await fails(-32602, later.call("file.upload", name="a.gcode", data="X", append=True))
    assert "was deleted" in deleted.message
    assert await later.call("file.list") == []
    await later.close()


async def test_api_md_chunks_after_a_restart_are_refused_and_the_file_stays_whole(
    tmp_path: Path,
) -> None:
    async with running_daemon(tmp_path) as hostd:
        rpc = await hostd.client()
        await rpc.call("file.upload", name="part.gcode", data="G0 X1\n")
        await rpc.call("file.upload", name="part.gcode", data="G0 X2\n", append=True)
        await rpc.close()

    async with running_daemon(tmp_path) as hostd:
        rpc = await hostd.client()
        refused = await fails(
            -32602, rpc.call("file.upload", name="part.gcode", data="G0 X3\n", append=True)
        )
        assert "the daemon restarted" in refused.message
        assert (hostd.jobs / "part.gcode").read_bytes() == b"G0 X1\nG0 X2\n"
        await rpc.close()


async def test_each_connection_forgets_its_uploads_when_it_leaves(
    rpc: Rpc, hostd: Running, monkeypatch: pytest.MonkeyPatch
) -> None:
    appends = hostd.api.appends
    forgotten = asyncio.Event()
    remember = appends.of

    def of(client: Client) -> Chain:
        chain = remember(client)
        client.on_disconnect.append(forgotten.set)  # runs after the Appends' own hook
        return chain

    monkeypatch.setattr(appends, "of", of)
    other = await hostd.client()
    await other.call("file.upload", name="a.gcode", data="G0\n")
    assert len(appends) == 1
    await other.close()
    async with asyncio.timeout(5):
        await forgotten.wait()
    assert len(appends) == 0


async def test_an_unknown_or_malformed_upload_id_is_refused(rpc: Rpc) -> None:
    unknown = await fails(1004, chunk(rpc, "a.gcode", "G0\n", "0" * 32, 0, True))
    assert "start the upload again" in unknown.message
    await fails(-32602, chunk(rpc, "a.gcode", "G0\n", "../../etc/passwd", 0, True))


async def test_over_the_quota_a_chunk_is_refused_staging_unchanged_and_a_retry_succeeds(
    tmp_path: Path,
) -> None:
    async with running_daemon(tmp_path, daemon={"jobs_quota": 100}) as hostd:
        rpc = await hostd.client()
        await rpc.call("file.upload", name="old.gcode", data="x" * 60)
        first = await rpc.call("file.upload", name="new.gcode", data="y" * 30, final=False)

        refused = await fails(1009, chunk(rpc, "new.gcode", "z" * 20, first["upload"], 30, False))

        assert refused.data == {"reason": "quota"}
        assert "quota of 100 bytes" in refused.message
        assert staged(hostd) == {first["upload"]: b"y" * 30}
        await rpc.call("file.delete", name="old.gcode")
        await chunk(rpc, "new.gcode", "z" * 20, first["upload"], 30, True)
        assert (hostd.jobs / "new.gcode").read_bytes() == b"y" * 30 + b"z" * 20
        await fails(1009, rpc.call("file.upload", name="big.gcode", data="w" * 51))
        assert [f["name"] for f in await rpc.call("file.list")] == ["new.gcode"]
        await rpc.close()


async def test_a_link_planted_at_the_staging_path_is_not_followed(
    rpc: Rpc, hostd: Running, tmp_path: Path
) -> None:
    secret = tmp_path / "secret"
    secret.write_text("not for clients\n")
    first = await rpc.call("file.upload", name="a.gcode", data="G0 X1\n", final=False)
    staging = hostd.jobs / ".staging" / first["upload"]
    staging.unlink()
    staging.symlink_to(secret)

    refused = await fails(1009, chunk(rpc, "a.gcode", "G0 X2\n", first["upload"], 6, True))

    assert "is gone or is a link" in refused.message and refused.data == {"reason": "io"}
    assert secret.read_text() == "not for clients\n"
    assert await rpc.call("file.list") == []
    await fails(1004, chunk(rpc, "a.gcode", "G0 X2\n", first["upload"], 6, True))


async def test_a_restart_mid_upload_publishes_nothing_and_forgets_the_upload(
    tmp_path: Path,
) -> None:
    async with running_daemon(tmp_path) as hostd:
        rpc = await hostd.client()
        await rpc.call("file.upload", name="part.gcode", data="old\n")
        first = await rpc.call("file.upload", name="part.gcode", data="G0 X1\n", final=False)
        await chunk(rpc, "part.gcode", "G0 X2\n", first["upload"], 6, False)
        assert len(staged(hostd)) == 1
        await rpc.close()

    async with running_daemon(tmp_path) as hostd:
        rpc = await hostd.client()
        assert staged(hostd) == {}
        assert (hostd.jobs / "part.gcode").read_bytes() == b"old\n"
        gone = await fails(1004, chunk(rpc, "part.gcode", "G0 X3\n", first["upload"], 12, True))
        assert "restarted" in gone.message
        assert [(f["name"], f["size"]) for f in await rpc.call("file.list")] == [("part.gcode", 4)]
        await rpc.close()


async def test_an_abandoned_upload_expires_and_its_id_is_then_unknown(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    clock = Clock()
    async with running_daemon(tmp_path, daemon={"upload_expiry": 60}, clock=clock) as hostd:
        rpc = await hostd.client()
        first = await rpc.call("file.upload", name="a.gcode", data="G0 X1\n", final=False)
        clock.now += 59
        await chunk(rpc, "a.gcode", "G0 X2\n", first["upload"], 6, False)
        clock.now += 60
        uploads = hostd.api.jobs.uploads
        expire, swept = uploads.expire, asyncio.Event()
        loop = asyncio.get_running_loop()

        def watched() -> list[str]:
            removed = expire()
            if removed:
                loop.call_soon_threadsafe(swept.set)
            return removed

        monkeypatch.setattr(uploads, "expire", watched)
        sweeper = asyncio.create_task(hostd.api.expire_uploads(0.01))  # as `hostd serve` runs it
        try:
            async with asyncio.timeout(5):
                await swept.wait()
        finally:
            sweeper.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await sweeper

        assert staged(hostd) == {}

        gone = await fails(1004, chunk(rpc, "a.gcode", "G0 X3\n", first["upload"], 12, True))
        assert "expired (60 s without a chunk)" in gone.message
        assert await rpc.call("file.list") == []
        await rpc.close()


async def test_api_md_chunks_without_a_connection_are_refused(hostd: Running) -> None:
    """A request no connection made (an MQTT command) has no upload of its own to continue."""
    assert hostd.api.methods is not None
    upload = hostd.api.methods["file.upload"].handler  # called as MQTT calls it: no client
    await upload(UploadParams(name="m.gcode", data="G0 X1\n"))

    with pytest.raises(RpcError) as refused:
        await upload(UploadParams(name="m.gcode", data="G0 X2\n", append=True))

    assert refused.value.code == -32602 and "without a connection" in refused.value.message
    assert (hostd.jobs / "m.gcode").read_bytes() == b"G0 X1\n"
