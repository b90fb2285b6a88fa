"""Upload gates that mutants of uploads.py and web/files.py once slipped through (docs/api.md,
"Uploads"; docs/web.md, `POST /files/<name>`).

Through a real daemon's socket or its real web server where a client sees
the behaviour; through `JobsDir` where the case needs the file system to
change under the daemon mid-call. What the disk holds is read from the disk.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import os
import stat
import types
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from structlog.testing import capture_logs

from hostd.api import uploads
from hostd.api.files import JobsDir
from hostd.api.uploads import STAGING, ChunkError, Uploads
from tests.daemon.conftest import Rpc, Running, running_daemon
from tests.daemon.test_api import fails
from tests.daemon.test_uploads import Clock
from tests.web.conftest import Web, running_web

BOUND = 10.0  # seconds: a bound for a test that would otherwise hang, not a timing check


def staged(jobs: Path) -> dict[str, bytes]:
    staging = jobs / STAGING
    return {p.name: p.read_bytes() for p in staging.iterdir()} if staging.exists() else {}


def uploads_os(monkeypatch: pytest.MonkeyPatch) -> types.SimpleNamespace:
    """uploads.py's own `os`, a copy to patch: the process's `os` stays as it is."""
    own = types.SimpleNamespace(**vars(os))
    monkeypatch.setattr(uploads, "os", own)
    return own


async def chunk(rpc: Rpc, name: str, data: str, upload: str, offset: int, final: bool) -> Any:
    return await rpc.call(
        "file.upload", name=name, data=data, upload=upload, offset=offset, final=final
    )


@pytest_asyncio.fixture
async def client(tmp_path: Path) -> AsyncIterator[tuple[Running, Rpc]]:
    async with running_daemon(tmp_path) as hostd:
        rpc = await hostd.client()
        yield hostd, rpc
        await rpc.close()


# -- retries and expiry -------------------------------------------------------


@pytest.mark.asyncio
async def test_a_retried_final_chunk_is_answered_until_the_expiry_then_it_is_1004(
    tmp_path: Path,
) -> None:
    """Published uploads are remembered `upload_expiry` seconds, as open ones are, and no
    longer: never reported abandoned, never answered forever."""
    clock = Clock()
    async with running_daemon(tmp_path, daemon={"upload_expiry": 60}, clock=clock) as hostd:
        rpc = await hostd.client()
        first = await rpc.call("file.upload", name="a.gcode", data="G0 X1\n", final=False)
        done = await chunk(rpc, "a.gcode", "G0 X2\n", first["upload"], 6, True)
        assert done == {"name": "a.gcode", "size": 12}

        clock.now += 59.5
        assert await chunk(rpc, "a.gcode", "G0 X2\n", first["upload"], 6, True) == done
        clock.now += 0.5  # upload_expiry since it was published

        assert await asyncio.to_thread(hostd.api.jobs.uploads.expire) == []  # not abandoned
        gone = await fails(1004, chunk(rpc, "a.gcode", "G0 X2\n", first["upload"], 6, True))
        assert first["upload"] in gone.message
        assert (hostd.jobs / "a.gcode").read_bytes() == b"G0 X1\nG0 X2\n"
        await rpc.close()


@pytest.mark.asyncio
async def test_a_retried_final_chunk_under_another_name_is_refused_and_publishes_nothing(
    client: tuple[Running, Rpc],
) -> None:
    hostd, rpc = client
    first = await rpc.call("file.upload", name="a.gcode", data="G0 X1\n", final=False)
    await chunk(rpc, "a.gcode", "G0 X2\n", first["upload"], 6, True)

    refused = await fails(1004, chunk(rpc, "b.gcode", "G0 X2\n", first["upload"], 6, True))

    assert "is finished" in refused.message
    assert [f["name"] for f in await rpc.call("file.list")] == ["a.gcode"]
    assert not (hostd.jobs / "b.gcode").exists()


# -- offsets ------------------------------------------------------------------


@pytest.mark.asyncio
@pytest.mark.parametrize("offset", [-1, -6])
async def test_a_negative_offset_is_invalid_params_and_changes_nothing(
    client: tuple[Running, Rpc], offset: int
) -> None:
    hostd, rpc = client
    first = await rpc.call("file.upload", name="a.gcode", data="G0 X1\n", final=False)

    await fails(-32602, chunk(rpc, "a.gcode", "G0 X1\n", first["upload"], offset, True))

    assert staged(hostd.jobs) == {first["upload"]: b"G0 X1\n"}
    assert await rpc.call("file.list") == []


@pytest.mark.asyncio
@pytest.mark.parametrize("offset", ["1", 1.0, True], ids=["string", "float", "bool"])
async def test_an_offset_that_is_not_a_json_integer_is_invalid_params(
    client: tuple[Running, Rpc], offset: Any
) -> None:
    """docs/api.md: every numeric parameter is a JSON number of its type, else -32602
    before anything is written (until this test, "1", 1.0 and true were offset 1)."""
    hostd, rpc = client
    first = await rpc.call("file.upload", name="a.gcode", data="G", final=False)

    refused = await fails(-32602, chunk(rpc, "a.gcode", "0 X1\n", first["upload"], offset, True))

    assert "offset" in refused.message
    assert staged(hostd.jobs) == {first["upload"]: b"G"}
    assert await rpc.call("file.list") == []


@pytest.mark.asyncio
@pytest.mark.parametrize("flag", ["final", "append"])
@pytest.mark.parametrize("value", ["false", 0, 1])
async def test_a_flag_that_is_not_a_json_boolean_is_invalid_params(
    client: tuple[Running, Rpc], flag: str, value: Any
) -> None:
    """`final: "false"` was read as false and `append: 1` as true (lax booleans): a client
    that meant otherwise had its file left unpublished, or appended to."""
    hostd, rpc = client
    refused = await fails(
        -32602, rpc.call("file.upload", name="a.gcode", data="G0", **{flag: value})
    )
    assert flag in refused.message
    assert staged(hostd.jobs) == {} and await rpc.call("file.list") == []


@pytest.mark.asyncio
@pytest.mark.parametrize("offset", [7, 106])
async def test_an_empty_chunk_past_the_staged_bytes_is_refused_with_the_expected_offset(
    client: tuple[Running, Rpc], offset: int
) -> None:
    hostd, rpc = client
    first = await rpc.call("file.upload", name="a.gcode", data="G0 X1\n", final=False)

    gap = await fails(-32602, chunk(rpc, "a.gcode", "", first["upload"], offset, False))

    assert gap.data == {"expected_offset": 6}
    assert staged(hostd.jobs) == {first["upload"]: b"G0 X1\n"}
    assert await chunk(rpc, "a.gcode", "", first["upload"], 6, True) == {
        "name": "a.gcode",
        "size": 6,
    }
    assert (hostd.jobs / "a.gcode").read_bytes() == b"G0 X1\n"


# -- names ------------------------------------------------------------------


@pytest.mark.asyncio
async def test_a_name_of_200_bytes_is_taken_and_one_byte_more_is_not(
    client: tuple[Running, Rpc],
) -> None:
    hostd, rpc = client
    for name in ("x" * 194 + ".gcode", "ü" * 98 + "x.nc"):  # 200 bytes each
        assert len(name.encode()) == 200
        assert (await rpc.call("file.upload", name=name, data="G0\n"))["size"] == 3
        assert (hostd.jobs / name).read_bytes() == b"G0\n"
    for name in ("x" * 195 + ".gcode", "ü" * 98 + "xx.nc"):  # 201 bytes each
        await fails(-32602, rpc.call("file.upload", name=name, data="G0\n"))
    assert len(await rpc.call("file.list")) == 2


@pytest.mark.asyncio
@pytest.mark.parametrize("char", ["\x7f", "\x1b", "\x01"], ids=["del", "esc", "soh"])
async def test_a_name_with_a_control_character_is_refused(
    client: tuple[Running, Rpc], char: str
) -> None:
    """A terminal listing the jobs directory must never be sent an escape sequence."""
    hostd, rpc = client
    refused = await fails(-32602, rpc.call("file.upload", name=f"a{char}[2J.nc", data="G0\n"))
    assert "control characters" in refused.message
    assert os.listdir(hostd.jobs) in ([], [STAGING])


# -- the staging and the directory ---------------------------------------------


@pytest.mark.asyncio
async def test_staging_grown_behind_the_daemons_back_is_discarded_not_published(
    client: tuple[Running, Rpc],
) -> None:
    hostd, rpc = client
    first = await rpc.call("file.upload", name="a.gcode", data="G0 X1\n", final=False)
    with (hostd.jobs / STAGING / first["upload"]).open("ab") as planted:
        planted.write(b"M3 S10000\n")  # the same file, longer than the upload left it

    refused = await fails(1009, chunk(rpc, "a.gcode", "G0 X2\n", first["upload"], 6, True))

    assert refused.data == {"reason": "io"} and "changed by something else" in refused.message
    assert await rpc.call("file.list") == [] and staged(hostd.jobs) == {}
    await fails(1004, chunk(rpc, "a.gcode", "G0 X2\n", first["upload"], 6, True))


@pytest.mark.asyncio
async def test_a_directory_left_in_staging_does_not_stop_uploads(
    client: tuple[Running, Rpc],
) -> None:
    hostd, rpc = client
    (hostd.jobs / STAGING / "leftover").mkdir(parents=True, exist_ok=True)

    assert await rpc.call("file.upload", name="a.gcode", data="G0\n") == {
        "name": "a.gcode",
        "size": 3,
    }
    assert (hostd.jobs / "a.gcode").read_bytes() == b"G0\n"


@pytest.mark.asyncio
async def test_an_append_to_a_name_that_is_a_link_reads_nothing_through_it(
    client: tuple[Running, Rpc], tmp_path: Path
) -> None:
    """The link is no job file: the append starts from nothing and the publish replaces it;
    the file it points to is never copied into the jobs directory, nor its size told."""
    hostd, rpc = client
    secret = tmp_path / "secret"
    secret.write_bytes(b"not for clients\n")
    (hostd.jobs / "link.gcode").symlink_to(secret)

    refused = await fails(
        -32602,
        rpc.call("file.upload", name="link.gcode", data="G0\n", append=True, offset=16),
    )
    assert refused.data == {"expected_offset": 0}
    assert (hostd.jobs / "link.gcode").is_symlink()

    done = await rpc.call("file.upload", name="link.gcode", data="G0\n", append=True, offset=0)

    assert done == {"name": "link.gcode", "size": 3}
    assert not (hostd.jobs / "link.gcode").is_symlink()
    assert (hostd.jobs / "link.gcode").read_bytes() == b"G0\n"
    assert secret.read_bytes() == b"not for clients\n"


@pytest.mark.asyncio
async def test_a_directory_flush_that_fails_is_1009_saying_the_file_is_published(
    client: tuple[Running, Rpc], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The rename is made durable by an fsync of the jobs directory; when that fails the
    client is told, with what became of the file."""
    hostd, rpc = client
    own = uploads_os(monkeypatch)
    synced: list[str] = []

    def fsync(fd: int) -> None:
        if stat.S_ISDIR(os.fstat(fd).st_mode):
            synced.append("directory")
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        synced.append("file")
        os.fsync(fd)

    own.fsync = fsync

    refused = await fails(1009, rpc.call("file.upload", name="a.gcode", data="G0 X1\n"))

    assert refused.data == {"reason": "io"}
    assert "'a.gcode' is published whole" in refused.message
    assert synced == ["file", "directory"]
    assert (hostd.jobs / "a.gcode").read_bytes() == b"G0 X1\n"
    assert staged(hostd.jobs) == {}


@pytest.mark.asyncio
@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EDQUOT, errno.EFBIG])
async def test_a_file_system_out_of_room_is_reported_full_whatever_its_errno(
    client: tuple[Running, Rpc], monkeypatch: pytest.MonkeyPatch, code: int
) -> None:
    """ENOSPC, the file system's own quota (EDQUOT) or its largest file (EFBIG): "full"."""
    hostd, rpc = client

    def write(fd: int, data: bytes | memoryview) -> int:
        raise OSError(code, os.strerror(code))

    uploads_os(monkeypatch).write = write

    refused = await fails(1009, rpc.call("file.upload", name="a.gcode", data="G0 X1\n"))

    assert refused.data == {"reason": "full"}
    assert await rpc.call("file.list") == [] and staged(hostd.jobs) == {}


@pytest.mark.asyncio
async def test_an_append_the_quota_cannot_hold_writes_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Replacing a file needs room for both versions: checked before the copy is made, so
    a quota that protects a small disk is never overrun, not even for the call's time."""
    async with running_daemon(tmp_path, daemon={"jobs_quota": 25}) as hostd:
        rpc = await hostd.client()
        await rpc.call("file.upload", name="a.gcode", data="0123456789" * 2)
        written: list[int] = []

        def write(fd: int, data: bytes | memoryview) -> int:
            written.append(len(data))
            return os.write(fd, data)

        uploads_os(monkeypatch).write = write

        refused = await fails(
            1009, rpc.call("file.upload", name="a.gcode", data="x", append=True, offset=20)
        )

        assert refused.data == {"reason": "quota"}
        assert written == []
        assert staged(hostd.jobs) == {}
        assert (hostd.jobs / "a.gcode").read_bytes() == b"0123456789" * 2
        await rpc.close()


@pytest.mark.timeout(BOUND)
def test_a_file_that_shrinks_while_an_append_copies_it_is_refused_not_a_hang(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Something outside the daemon cuts the file in place while its copy is read: the
    copy ends short, the chunk is refused and nothing is published (the lock is freed)."""
    (tmp_path / "jobs").mkdir()
    jobs = JobsDir(tmp_path / "jobs")
    jobs.upload("a.gcode", b"0123456789")
    opened = Uploads._published

    def published(self: Uploads, jobs_fd: int, name: str) -> tuple[int | None, int]:
        source, size = opened(self, jobs_fd, name)
        os.truncate(tmp_path / "jobs" / name, 3)  # after its size was read
        return source, size

    monkeypatch.setattr(Uploads, "_published", published)

    with pytest.raises(ChunkError) as refused:
        jobs.upload("a.gcode", b"x", append=True, offset=10)
    # The hint (`expected_offset`) is where an append may go on from: the file's size now.
    assert refused.value.expected == 3 and "it has 3 bytes now" in str(refused.value)

    assert (tmp_path / "jobs" / "a.gcode").read_bytes() == b"012"
    assert staged(tmp_path / "jobs") == {}
    monkeypatch.undo()
    assert jobs.upload("b.gcode", b"G0\n").size == 3  # the directory's lock is free


# -- the web upload (POST /files/<name>) and download --------------------------


@contextlib.asynccontextmanager
async def posting(
    web: Web, name: str, length: int
) -> AsyncIterator[tuple[asyncio.StreamReader, asyncio.StreamWriter]]:
    """A raw `POST /files/<name>` whose body the test sends itself; closed at the end, so
    that a handler still reading it ends too."""
    reader, writer = await asyncio.open_connection("127.0.0.1", web.server.port)
    writer.write(
        f"POST /files/{name} HTTP/1.1\r\nHost: 127.0.0.1\r\n"
        f"Authorization: Bearer {web.token}\r\nContent-Length: {length}\r\n\r\n".encode()
    )
    try:
        yield reader, writer
    finally:
        writer.close()


async def status(reader: asyncio.StreamReader) -> int:
    async with asyncio.timeout(BOUND):
        line = await reader.readline()
    assert line.startswith(b"HTTP/1.1 "), line
    return int(line.split()[1])


def calls_of(
    jobs: JobsDir, monkeypatch: pytest.MonkeyPatch, loop: asyncio.AbstractEventLoop
) -> asyncio.Event:
    """Set once the web upload has staged a chunk (its `JobsDir.upload` call returned)."""
    staged_one = asyncio.Event()
    upload = jobs.upload

    def watched(*args: Any, **kwargs: Any) -> Any:
        done = upload(*args, **kwargs)
        loop.call_soon_threadsafe(staged_one.set)
        return done

    monkeypatch.setattr(jobs, "upload", watched)
    return staged_one


@pytest.mark.asyncio
async def test_a_web_upload_that_succeeds_is_not_logged_as_failed(tmp_path: Path) -> None:
    async with running_web(tmp_path) as web:
        with capture_logs() as logs:
            async with web.session.post(
                f"{web.url}/files/a.nc", data=b"G0 X1\n", headers=web.auth()
            ) as r:
                assert r.status == 200
        events = [e["event"] for e in logs]
        assert "web upload" in events
        assert "web upload failed; staging removed" not in events


@pytest.mark.asyncio
async def test_a_web_upload_whose_body_stalls_is_408_and_leaves_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    async with running_web(tmp_path, idle_timeout=0.5) as web:
        staged_one = calls_of(web.hostd.api.jobs, monkeypatch, asyncio.get_running_loop())
        async with posting(web, "stall.nc", 1000) as (reader, writer):
            writer.write(b"G0 X1\n")
            async with asyncio.timeout(BOUND):
                await staged_one.wait()  # a chunk is in staging

            assert await status(reader) == 408  # the rest of the body never comes

        assert staged(web.hostd.jobs) == {}
        assert not (web.hostd.jobs / "stall.nc").exists()


@pytest.mark.asyncio
async def test_a_web_upload_whose_staging_expired_mid_body_is_408_and_leaves_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A body that pauses `upload_expiry` between two reads (an expiry set shorter than
    `idle_timeout`): its upload is gone, and the sender is told so with a 408, not a 500."""
    clock = Clock()
    daemon: dict[str, Any] = {"daemon": {"upload_expiry": 60}, "clock": clock}
    async with running_web(tmp_path, machine=daemon) as web:
        staged_one = calls_of(web.hostd.api.jobs, monkeypatch, asyncio.get_running_loop())
        first, rest = b"G0 X1\n" * 10, b"G0 X2\n" * 10
        async with posting(web, "slow.nc", len(first) + len(rest)) as (reader, writer):
            writer.write(first)
            async with asyncio.timeout(BOUND):
                await staged_one.wait()
            clock.now += 60  # upload_expiry without a chunk, the connection still open
            writer.write(rest)

            assert await status(reader) == 408

        assert staged(web.hostd.jobs) == {}
        assert not (web.hostd.jobs / "slow.nc").exists()


@pytest.mark.asyncio
async def test_a_link_in_the_jobs_directory_is_never_served(tmp_path: Path) -> None:
    secret = tmp_path / "secret"
    secret.write_text("not for clients\n")
    async with running_web(tmp_path) as web:
        (web.hostd.jobs / "link.nc").symlink_to(secret)
        async with web.session.get(f"{web.url}/files/link.nc", headers=web.auth()) as r:
            assert r.status == 404
            assert "not for clients" not in await r.text()
        async with web.session.get(f"{web.url}/files/.staging", headers=web.auth()) as r:
            assert r.status == 400
