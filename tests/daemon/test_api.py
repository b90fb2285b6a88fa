"""Every api.md method through a real Unix socket, against a daemon with a simulated machine."""

from __future__ import annotations

import asyncio
import base64
import itertools
import json
import re
from pathlib import Path
from typing import Any

import pytest

from tests.daemon.conftest import Rpc, RpcFailure, Running, running_daemon

pytestmark = pytest.mark.asyncio

SNAPSHOT_KEYS = {
    "id",
    "dialect",
    "supervisor",
    "state",
    "position",
    "line",
    "velocity",
    "feed",
    "units",
    "homed",
    "indicator",
    "faults",
    "job",
    "last_exception",
}
JOB_KEYS = {
    "id",
    "machine",
    "file",
    "kind",
    "state",
    "lines_total",
    "lines_sent",
    "lines_acked",
    "started_at",
    "ended_at",
    "error",
    "line_executed",
    "start_line",
    "preamble",
    "tool_changes",
    "file_sha256",
}


async def fails(code: int, call: object) -> RpcFailure:
    with pytest.raises(RpcFailure) as err:
        await call  # type: ignore[misc]
    assert err.value.code == code, err.value
    assert err.value.message
    return err.value


async def job_end(rpc: Rpc, job_id: int, timeout: float = 30) -> dict[str, object]:
    """The job's end as told; `timeout` bounds a hang (Rpc.notification)."""
    note = await rpc.notification(
        lambda n: (
            n["method"] == "job"
            and n["params"]["job"]["id"] == job_id
            and n["params"]["job"]["state"] not in ("running", "paused")
        ),
        timeout,
    )
    job: dict[str, object] = note["params"]["job"]
    return job


async def test_daemon_info_and_machine_list(rpc: Rpc) -> None:
    info = await rpc.call("daemon.info")
    assert info["api"] == 1 and info["machines"] == ["sim1"] and info["version"]
    (entry,) = await rpc.call("machine.list")
    assert entry["id"] == "sim1" and entry["dialect"] == "g2core"
    assert entry["supervisor"] == "idle"
    assert entry["state"]["name"] in ("READY", "PROGRAM_STOP", "PROGRAM_END")


async def test_the_snapshot_has_every_field_of_api_md(rpc: Rpc) -> None:
    snap = await rpc.call("machine.status", machine="sim1")
    assert set(snap) >= SNAPSHOT_KEYS
    assert snap["units"] == "mm" and snap["indicator"] == "normal"
    assert set(snap["position"]) >= {"x", "y", "z"}


async def test_machine_ids(rpc: Rpc) -> None:
    await fails(1001, rpc.call("machine.status", machine="nope"))
    await fails(-32602, rpc.call("machine.status", machine="../etc"))
    await fails(-32602, rpc.call("machine.status"))


async def test_send_answers_queries_and_gcode(rpc: Rpc) -> None:
    answer = await rpc.call("machine.send", machine="sim1", line="{xvm:n}")
    assert answer["status"] == 0 and "xvm" in answer["r"]
    answer = await rpc.call("machine.send", machine="sim1", line="G0 X3")
    assert answer == {"status": 0, "r": answer["r"]}


async def test_send_errors(rpc: Rpc) -> None:
    err = await fails(1005, rpc.call("machine.send", machine="sim1", line="G5 X1"))
    assert err.data["status"] != 0 and err.data["msg"]
    err = await fails(-32602, rpc.call("machine.send", machine="sim1", line="G0 X1\u0000"))
    assert "NUL" in err.message
    await fails(-32602, rpc.call("machine.send", machine="sim1", line="$$"))
    await fails(-32602, rpc.call("machine.send", machine="sim1", line="G0", timeout=-1))


async def test_alarm_rejects_actions_until_clear(rpc: Rpc) -> None:
    await rpc.call("subscribe", topics=["exception", "status"], machine="sim1")
    assert await rpc.call("machine.alarm", machine="sim1") == {}
    await rpc.notification(lambda n: n["method"] == "exception")
    await rpc.notification(
        lambda n: n["method"] == "status" and n["params"]["snapshot"]["state"]["name"] == "ALARM"
    )
    await fails(204, rpc.call("machine.send", machine="sim1", line="G0 X1"))
    await fails(204, rpc.call("machine.jog", machine="sim1", axes={"x": 1}, feed=100))
    assert (await rpc.call("machine.send", machine="sim1", line="{xvm:n}"))["status"] == 0
    # The snapshot says what locks the machine out and what ends it, not only the faults.
    locked = (await rpc.call("machine.status", machine="sim1"))["lockout"]
    assert locked["state"] == "ALARM" and locked["clear"] == "machine.clear"
    assert locked["message"] and locked["message"] != "alarm"
    assert await rpc.call("machine.clear", machine="sim1") == {}
    snap = await rpc.call("machine.status", machine="sim1")
    assert snap["state"]["name"] == "PROGRAM_STOP"
    assert snap["lockout"] is None
    assert snap["last_exception"]["st"] == 18


async def test_settings_are_read_in_every_lockout_without_a_job_row(rpc: Rpc) -> None:
    await rpc.call("subscribe", topics=["status"], machine="sim1")
    before = await rpc.call("job.list", machine="sim1")
    for raise_it, name in (("machine.alarm", "ALARM"), ("machine.shutdown", "SHUTDOWN")):
        await rpc.call(raise_it, machine="sim1")
        await rpc.notification(
            lambda n, name=name: (
                n["method"] == "status" and n["params"]["snapshot"]["state"]["name"] == name
            )
        )
        assert await rpc.call("settings.get", machine="sim1", keys=["xvm", "yvm"]) == {
            "xvm": 6000,
            "yvm": 6000,
        }
        await fails(
            205 if name == "SHUTDOWN" else 204,
            rpc.call("settings.set", machine="sim1", values={"xvm": 1}),
        )
    assert await rpc.call("job.list", machine="sim1") == before


async def test_pause_resume_cancel_of_an_ended_job_are_refused(rpc: Rpc) -> None:
    await rpc.call("file.upload", name="short.gcode", data="G1 X1 F3000\nG1 X0\n")
    await rpc.call("subscribe", topics=["job"], machine="sim1")
    started = await rpc.call("job.start", machine="sim1", file="short.gcode")
    assert (await job_end(rpc, started["job"]))["state"] == "completed"
    for method in ("job.pause", "job.resume", "job.cancel"):
        await fails(1003, rpc.call(method, machine="sim1"))
    assert (await rpc.call("job.get", job=started["job"]))["state"] == "completed"


async def test_shutdown_and_reset(rpc: Rpc, hostd: Running) -> None:
    await rpc.call("machine.shutdown", machine="sim1")
    await fails(205, rpc.call("machine.send", machine="sim1", line="M30"))
    assert await rpc.call("machine.reset", machine="sim1") == {}
    snap = await rpc.call("machine.status", machine="sim1")
    assert snap["state"]["name"] == "READY"


async def test_files(rpc: Rpc, hostd: Running) -> None:
    assert await rpc.call("file.upload", name="a.gcode", data="G0 X1\n") == {
        "name": "a.gcode",
        "size": 6,
    }
    raw = base64.b64encode(b"G0 X2\n").decode()
    await rpc.call("file.upload", name="b.gcode", data=raw, encoding="base64")
    first = await rpc.call("file.upload", name="c.gcode", data="G0 X1\n", final=False)
    assert first == {"name": "c.gcode", "size": 6, "upload": first["upload"]}
    assert await rpc.call(
        "file.upload", name="c.gcode", data="G0 X2\n", upload=first["upload"], offset=6
    ) == {"name": "c.gcode", "size": 12}
    files = await rpc.call("file.list")
    assert [(f["name"], f["size"]) for f in files] == [
        ("a.gcode", 6),
        ("b.gcode", 6),
        ("c.gcode", 12),
    ]
    assert await rpc.call("file.delete", name="a.gcode") == {}
    await fails(1004, rpc.call("file.delete", name="a.gcode"))
    for name in ("../x", "/etc/passwd", "a/b", "..", ".hidden"):
        await fails(-32602, rpc.call("file.upload", name=name, data="x"))
        await fails(-32602, rpc.call("job.start", machine="sim1", file=name))
    await fails(-32602, rpc.call("file.upload", name="d.gcode", data="%%%", encoding="base64"))
    assert not (hostd.jobs.parent / "x").exists()


async def test_a_job_runs_and_is_reported(rpc: Rpc, hostd: Running) -> None:
    moves = "".join(f"G1 X{(i % 2) * 10} Y{i % 3} F6000\n" for i in range(40))
    program = "(square)\nG21 G90\n" + moves
    await rpc.call("file.upload", name="square.gcode", data=program)
    await rpc.call("subscribe", topics=["job", "supervisor"], machine="sim1")
    started = await rpc.call("job.start", machine="sim1", file="square.gcode")
    job = await job_end(rpc, started["job"])
    assert job["state"] == "completed"
    assert job["lines_total"] == job["lines_sent"] == job["lines_acked"] == 41
    row = await rpc.call("job.get", job=started["job"])
    assert set(row) == JOB_KEYS
    assert row["state"] == "completed" and row["error"] is None and row["file"] == "square.gcode"
    listed = await rpc.call("job.list", machine="sim1")
    assert listed[0]["id"] == started["job"]
    await fails(1004, rpc.call("job.get", job=99999))


async def test_a_jobs_total_is_its_sendable_lines_from_its_start(rpc: Rpc, hostd: Running) -> None:
    """Counted by the job's check in its pass over the file, or, with `force` (no check),
    by the job itself: the same count either way, from any start line."""
    moves = "".join(f"G1 X{i} F6000\n" for i in range(10))  # lines 4-13
    await rpc.call("file.upload", name="t.gcode", data="(a comment)\nG21 G90\n\n" + moves + "%\n")
    await rpc.call("subscribe", topics=["job"], machine="sim1")
    for params, total in (
        ({}, 11),
        ({"force": True}, 11),
        ({"start_line": 6, "restore": False}, 8),
        ({"start_line": 6, "restore": False, "force": True}, 8),
    ):
        started = await rpc.call("job.start", machine="sim1", file="t.gcode", **params)
        job = await job_end(rpc, started["job"])
        assert job["state"] == "completed", params
        assert job["lines_total"] == job["lines_acked"] == total, params
    await fails(1004, rpc.call("job.start", machine="sim1", file="missing.gcode"))


async def test_job_pause_resume_cancel(rpc: Rpc) -> None:
    program = "".join(f"G1 X{i % 30} F1200\n" for i in range(200))
    await rpc.call("file.upload", name="long.gcode", data=program)
    await rpc.call("subscribe", topics=["job"], machine="sim1")
    started = await rpc.call("job.start", machine="sim1", file="long.gcode")
    await fails(1003, rpc.call("job.start", machine="sim1", file="long.gcode"))
    await fails(1003, rpc.call("machine.send", machine="sim1", line="G0 X0"))
    paused = await rpc.call("job.pause", machine="sim1")
    assert paused["state"] == "paused" and paused["id"] == started["job"]
    assert (await rpc.call("machine.status", machine="sim1"))["supervisor"] == "paused"
    resumed = await rpc.call("job.resume", machine="sim1")
    assert resumed["state"] == "running"
    cancelled = await rpc.call("job.cancel", machine="sim1")
    assert cancelled["state"] == "cancelled"
    await fails(1003, rpc.call("job.resume", machine="sim1"))
    # Across pause, resume and cancel, no notification's counts ever went backwards.
    await rpc.call("daemon.info")  # every notification sent so far is in the queue now
    jobs = []
    while not rpc.notifications.empty():
        jobs.append(rpc.notifications.get_nowait()["params"]["job"])
    assert [j["state"] for j in jobs][-1] == "cancelled"
    for earlier, later in itertools.pairwise(jobs):
        assert later["lines_acked"] >= earlier["lines_acked"]
        assert later["lines_sent"] >= earlier["lines_sent"]


async def test_jog_and_settings(rpc: Rpc) -> None:
    await rpc.call("subscribe", topics=["job"], machine="sim1")
    jog = await rpc.call("machine.jog", machine="sim1", axes={"x": 2.5}, feed=3000)
    assert (await job_end(rpc, jog["job"]))["state"] == "completed"
    await fails(-32602, rpc.call("machine.jog", machine="sim1", axes={"q": 1}, feed=10))
    assert await rpc.call("settings.set", machine="sim1", values={"xvm": 9000}) == {"xvm": 9000}
    assert await rpc.call("settings.get", machine="sim1", keys=["xvm", "yvm"]) == {
        "xvm": 9000,
        "yvm": await _yvm(rpc),
    }
    kinds = [j["kind"] for j in await rpc.call("job.list", machine="sim1")]
    assert kinds[:3] == ["settings", "settings", "settings"] or "jog" in kinds


@pytest.mark.parametrize(
    ("method", "params"),
    [
        ("machine.jog", {"axes": {"x": 1e300}, "feed": 100}),
        ("machine.jog", {"axes": {"x": 1}, "feed": 1e300}),
        ("machine.jog", {"axes": {"x": 1}, "feed": 1e-300}),
        ("machine.jog", {"axes": {"x": 1}, "feed": 2**53}),
        ("machine.jog", {"axes": {"x": 1}, "feed": 1_000_000.001}),  # MAX_FEED, just past
        ("job.start", {"file": "a.gcode", "start_line": 2**53}),
        ("settings.set", {"values": {"xvm": "9" * 600}}),
        ("settings.set", {"values": {"flash": 1}}),
        ("settings.get", {"keys": ["boot"]}),
        ("machine.send", {"line": "G0 X1", "timeout": 10**400}),
    ],
    ids=[
        "jog-100-m-and-more",
        "jog-feed-huge",
        "jog-feed-tiny",
        "jog-feed-past-2**53",
        "jog-feed-just-past-its-bound",
        "start-line-past-2**53",
        "setting-over-511-bytes",
        "set-bootloader",
        "get-bootloader",
        "timeout-400-digits",
    ],
)
async def test_params_out_of_range_are_refused_before_anything_is_sent(
    rpc: Rpc, hostd: Running, method: str, params: dict[str, object]
) -> None:
    before = await rpc.call("job.list", machine="sim1")
    await fails(-32602, rpc.call(method, machine="sim1", **params))
    assert await rpc.call("job.list", machine="sim1") == before  # no operation was begun
    assert (await rpc.call("machine.status", machine="sim1"))["supervisor"] == "idle"


async def _yvm(rpc: Rpc) -> object:
    return (await rpc.call("machine.send", machine="sim1", line="{yvm:n}"))["r"]["yvm"]


async def test_subscriptions_deliver_topics_and_stop_after_unsubscribe(rpc: Rpc) -> None:
    sub = await rpc.call("subscribe", topics=["status", "console"], machine="sim1")
    await rpc.call("machine.send", machine="sim1", line="G0 X4")
    # In the order they happen: the line goes out, then the board reports the move.
    console = await rpc.notification(
        lambda n: n["method"] == "console" and n["params"]["text"] == "G0 X4"
    )
    assert console["params"]["direction"] == "tx" and console["params"]["channel"] == "data"
    status = await rpc.notification(lambda n: n["method"] == "status")
    assert status["params"]["machine"] == "sim1" and "report" in status["params"]
    assert await rpc.call("unsubscribe", subscription=sub["subscription"]) == {}
    await fails(-32602, rpc.call("unsubscribe", subscription=sub["subscription"]))
    await fails(-32602, rpc.call("subscribe", topics=["weather"]))
    await fails(1001, rpc.call("subscribe", topics=["status"], machine="nope"))


async def _drained(rpc: Rpc, until: str = "fbc") -> list[dict[str, Any]]:
    """The console notifications this client was sent, in order, up to the board's answer
    to the operator's last line (it names `until`). Every subscriber is sent the same
    stream in the same order, so clients drained so are cut at the same line: drained
    "until now" instead, a report that came between two clients' drains was in one list
    and not the other."""
    out = []
    async with asyncio.timeout(30):
        while True:
            note = await rpc.notifications.get()
            if note["method"] == "console":
                out.append(note["params"])
                params = note["params"]
                if params["direction"] == "rx" and until in params["text"]:
                    return out


async def test_a_console_subscription_can_leave_out_a_jobs_own_lines(
    hostd: Running, rpc: Rpc
) -> None:
    # Moves long enough for the simulated board, each line told apart by its X.
    moves = [f"G1 X{i}.25 Y{i % 3} F3000" for i in range(1, 31)]
    await rpc.call("file.upload", name="lines.gcode", data="G21 G90\n" + "\n".join(moves))
    lean, watcher = await hostd.client(), await hostd.client()
    try:
        await rpc.call("subscribe", topics=["console"], machine="sim1")
        await lean.call("subscribe", topics=["console"], machine="sim1", job_lines=False)
        await fails(-32602, lean.call("subscribe", topics=["console"], job_lines="no"))
        await watcher.call("subscribe", topics=["job"], machine="sim1")
        started = await rpc.call("job.start", machine="sim1", file="lines.gcode")
        assert (await job_end(watcher, started["job"]))["state"] == "completed"
        await rpc.call("machine.send", machine="sim1", line="{fbc:n}")  # the operator's own
        full = await _drained(rpc)
        kept = await _drained(lean)
    finally:
        await lean.close()
        await watcher.close()

    # The default, as api.md says: every job line written, and an answer for each.
    sent = [n["text"] for n in full if n["direction"] == "tx"]
    for move in moves:
        assert sum(move in text for text in sent) == 1, move
    # Without the job's lines: what is left is the rest of the same stream, in its order.
    rest = iter(full)
    assert all(any(n == m for m in rest) for n in kept), "not a subsequence of the full console"
    left_out = list(full)
    for n in kept:
        left_out.remove(n)
    tx_out = [n["text"] for n in left_out if n["direction"] == "tx"]
    rx_out = [n["text"] for n in left_out if n["direction"] == "rx"]
    assert len(tx_out) == len(moves) + 1  # the job's lines, its `G21 G90` too
    assert all(move in text for move, text in zip(moves, tx_out[1:], strict=True))
    assert len(rx_out) == len(tx_out)  # one plain answer each, nothing else
    assert all(json.loads(text)["f"][1] == 0 for text in rx_out)  # status 0 every one
    # The operator's line and its answer still come.
    assert any(n["direction"] == "tx" and "fbc" in n["text"] for n in kept)
    assert any(n["direction"] == "rx" and "fbc" in n["text"] for n in kept)


def _status_traffic(note: dict[str, Any]) -> bool:
    """The dashboard's own test (app.js isStatusTraffic): a status poll or report."""
    text = note["text"].strip()
    if note["direction"] == "tx":
        return re.fullmatch(r'\{\s*"?sr"?\s*:\s*(n|null|"")\s*\}', text, re.I) is not None
    return text.startswith(('{"sr":', '{"r":{"sr":'))


async def test_a_console_subscription_can_leave_out_status_traffic(
    hostd: Running, rpc: Rpc
) -> None:
    quiet = await hostd.client()
    try:
        await rpc.call("subscribe", topics=["console"], machine="sim1")
        await quiet.call("subscribe", topics=["console"], machine="sim1", status_traffic=False)
        await fails(-32602, quiet.call("subscribe", topics=["console"], status_traffic="no"))
        await rpc.call("machine.send", machine="sim1", line="G1 X5 F3000")  # reported moving
        await rpc.call("machine.send", machine="sim1", line="{sr:n}")  # the operator's poll
        await rpc.call("machine.send", machine="sim1", line="{fbc:n}")
        full = await _drained(rpc)
        kept = await _drained(quiet)
    finally:
        await quiet.close()
    polls = [n for n in full if _status_traffic(n)]
    assert any(n["direction"] == "tx" for n in polls) and any(
        n["direction"] == "rx" for n in polls
    ), full
    # Exactly the status traffic is gone; the rest is the same stream in the same order.
    assert kept == [n for n in full if not _status_traffic(n)]
    texts = [n["text"] for n in kept]
    assert "G1 X5 F3000" in texts and '{"fbc":null}' in texts  # as written: strict JSON
    assert any("fbc" in text for text in texts if text.startswith('{"r":'))  # its answer


async def test_a_client_cannot_end_another_clients_subscription(hostd: Running, rpc: Rpc) -> None:
    sub = await rpc.call("subscribe", topics=["console"], machine="sim1")
    other = await hostd.client()
    try:
        # Ids are small integers: a client that guesses one must not silence another's watch.
        await fails(-32602, other.call("unsubscribe", subscription=sub["subscription"]))
    finally:
        await other.close()
    await rpc.call("machine.send", machine="sim1", line="G0 X2")
    await rpc.notification(lambda n: n["method"] == "console" and n["params"]["text"] == "G0 X2")
    assert await rpc.call("unsubscribe", subscription=sub["subscription"]) == {}


async def test_faults_are_listed(rpc: Rpc) -> None:
    faults = await rpc.call("fault.list", machine="sim1")
    assert len(faults) == 10 and not any(f["active"] for f in faults)
    assert set(faults[0]) == {
        "id",
        "severity",
        "active",
        "overridden",
        "overridable",
        "since",
        "value",
        "message",
        "clears",  # added: how it ends (docs/api.md)
    }
    await fails(-32602, rpc.call("fault.clear", machine="sim1", fault="nope"))


async def test_connect_and_disconnect(rpc: Rpc) -> None:
    snap = await rpc.call("machine.disconnect", machine="sim1")
    assert snap["supervisor"] == "disconnected"
    await fails(1002, rpc.call("machine.send", machine="sim1", line="{xvm:n}"))
    snap = await rpc.call("machine.connect", machine="sim1")
    assert snap["supervisor"] in ("busy", "idle")


async def test_a_subscriber_that_never_reads_does_not_slow_a_job_or_others(
    tmp_path: Path,
) -> None:
    async with running_daemon(tmp_path) as hostd:
        rpc = await hostd.client()
        await hostd.idle(rpc)
        sleeper = await hostd.client()
        await sleeper.call("subscribe", topics=["status", "console", "job"])
        sleeper._task.cancel()  # it stops reading its socket from here on
        # Lines the board takes at once and that do not move it: the test is about the
        # stream, not the motion (5,000 moves this short would starve a planner).
        program = "".join(f"G{90 + i % 2}\n" for i in range(5000))
        await rpc.call("file.upload", name="big.gcode", data=program)
        await rpc.call("subscribe", topics=["job"], machine="sim1")
        started = await rpc.call("job.start", machine="sim1", file="big.gcode")
        for _ in range(20):  # round trips stay answered while the job streams
            await asyncio.wait_for(rpc.call("daemon.info"), 2)
        # 5,000 round trips of a 4-line window: past 30 s under load (3,771 in 30 s at
        # load average 12-16 on two cores). The job's own bound, not the notification's.
        job = await job_end(rpc, started["job"], timeout=55)
        assert job["state"] == "completed" and job["lines_acked"] == 5000
        await rpc.close()
        await sleeper.close()


async def test_overlapping_subscriptions_deliver_each_notification_once(rpc: Rpc) -> None:
    await rpc.call("subscribe", topics=["supervisor"], machine="sim1")
    await rpc.call("subscribe", topics=["supervisor", "job"])
    await rpc.call("machine.disconnect", machine="sim1")
    first = await rpc.notification(lambda n: n["method"] == "supervisor")
    assert first["params"]["to"] == "disconnected"
    await rpc.call("daemon.info")  # answers follow every notification queued before them
    assert rpc.notifications.empty(), "the same notification arrived twice"


async def test_panic_refuses_everything_but_reset(rpc: Rpc) -> None:
    await rpc.call("machine.send", machine="sim1", line="{panic:n}")
    await fails(206, rpc.call("machine.send", machine="sim1", line="G0 X1"))
    await fails(206, rpc.call("machine.clear", machine="sim1"))
    await fails(206, rpc.call("machine.cycle_start", machine="sim1"))
    assert await rpc.call("machine.reset", machine="sim1") == {}
    assert (await rpc.call("machine.status", machine="sim1"))["state"]["name"] == "READY"


async def test_a_board_that_does_not_answer_in_time_is_1006(rpc: Rpc, hostd: Running) -> None:
    sim = hostd.daemon.sims["sim1"]
    sim.stop_reading()  # the line stays unread: no answer comes
    err = await fails(1006, rpc.call("machine.send", machine="sim1", line="{xvm:n}", timeout=0.3))
    assert "0.3" in err.message
    sim.resume_reading()
    assert (await rpc.call("machine.send", machine="sim1", line="{yvm:n}"))["status"] == 0


async def test_a_probe_result_reaches_the_snapshot_and_its_topic(rpc: Rpc, hostd: Running) -> None:
    sim = hostd.daemon.sims["sim1"]
    snap = await rpc.call("machine.status", machine="sim1")
    assert snap["probe"] is None
    await rpc.call("subscribe", topics=["probe"], machine="sim1")
    # The simulated board probes as cycle_probing.cpp does and prints its report.
    sim.probe_surface("z", -1.00312)
    await rpc.call("machine.send", machine="sim1", line="G0 X12.5 Y-3.25")
    await rpc.call("machine.send", machine="sim1", line="G38.2 Z-5 F300")
    note = await rpc.notification(lambda n: n["method"] == "probe")
    position = {"x": 12.5, "y": -3.25, "z": -1.00312, "a": 0.0, "b": 0.0, "c": 0.0}
    assert note["params"]["probe"] == {"ok": True, "position": position}
    snap = await rpc.call("machine.status", machine="sim1")
    assert snap["probe"]["ok"] is True and snap["probe"]["position"]["z"] == -1.00312
    sim.probe_surface(None)  # G38.3: a probe that may miss without an alarm
    await rpc.call("machine.send", machine="sim1", line="G38.3 Z-3 F300")
    note = await rpc.notification(lambda n: n["method"] == "probe")
    assert note["params"]["probe"]["ok"] is False
