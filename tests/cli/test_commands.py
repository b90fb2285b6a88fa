"""The `hostd` client commands, run as a user runs them: subprocesses against `hostd serve`.

Every test shares one daemon and its simulated machine `sim1` (started once
for the module), and starts from the machine idle.
"""

from __future__ import annotations

import asyncio
import json
import subprocess
from pathlib import Path

import pytest

from hostd.cli.client import Client
from hostd.cli.commands import UPLOAD_CHUNK, upload
from tests.cli.conftest import MACHINE, Daemon, Spawned

SMALL = "G21 G90\nG0 X1 Y1\n(a comment, not counted)\nG1 X2 F3000\n\nG1 Y2\nM2\n"
REJECTED = "G21 G90\nG0 X1\nG99 (the simulated g2core does not know it)\nG0 X2\nM2\n"
# Sixteen 20 mm moves at 600 mm/min: about 3 s on the daemon's 10x simulated board,
# long enough to be interrupted and short enough to let finish.
LONG = "G21 G90\nG1 F600\n" + "G1 X20\nG1 X0\n" * 8 + "M2\n"  # ~3 s on the x10 board
# For a job the test cancels in the end (so its length costs nothing): it must outlast
# the CLI processes the test starts meanwhile, seconds each on a loaded machine (the
# 3 s LONG ended before `hostd cancel` connected, at load average 17).
ENDLESS = "G21 G90\nG1 F600\n" + "G1 X20\nG1 X0\n" * 150 + "M2\n"  # ~60 s


@pytest.fixture(scope="module")
def completed(
    daemon: Daemon, tmp_path_factory: pytest.TempPathFactory
) -> subprocess.CompletedProcess[str]:
    """`hostd run` of a small file, once for the module: several tests look at its job."""
    daemon.wait_idle()
    path = tmp_path_factory.mktemp("files") / "small.gcode"
    path.write_text(SMALL, encoding="utf-8")
    return daemon.cli("run", str(path), "--machine", MACHINE)


# -- status --------------------------------------------------------------------


def test_status_shows_a_row_per_machine(idle: Daemon) -> None:
    result = idle.cli("status")

    assert result.returncode == 0, result.stderr
    header, row = result.stdout.splitlines()
    assert header.split() == ["MACHINE", "SUPERVISOR", "STATE", "POSITION", "JOB"]
    assert row.split()[:2] == [MACHINE, "idle"]


def test_status_json_is_the_raw_snapshots(idle: Daemon) -> None:
    every = idle.cli("status", "--json")
    one = idle.cli("--json", "status", MACHINE)

    assert every.returncode == 0 and one.returncode == 0, every.stderr + one.stderr
    [snapshot] = json.loads(every.stdout)
    assert snapshot["id"] == MACHINE and snapshot["supervisor"] == "idle"
    assert json.loads(one.stdout)["state"]["name"] == snapshot["state"]["name"]


def test_status_of_one_machine_reads_as_key_and_value(idle: Daemon) -> None:
    result = idle.cli("status", MACHINE)

    assert result.returncode == 0, result.stderr
    fields = dict(line.split(None, 1) for line in result.stdout.splitlines() if " " in line)
    assert fields["machine"] == f"{MACHINE} (g2core)"
    assert fields["supervisor"] == "idle"


def test_an_unknown_machine_is_error_1001(idle: Daemon) -> None:
    result = idle.cli("status", "nope")

    assert result.returncode == 1
    assert "1001" in result.stderr and "nope" in result.stderr
    assert result.stdout == ""


# -- send ----------------------------------------------------------------------


def test_send_prints_the_controllers_answer_to_a_query_as_keys_and_values(
    idle: Daemon,
) -> None:
    result = idle.cli("send", MACHINE, '{"sr":null}', '{"xvm":null}')

    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines.count("ok") == 2  # each answer's status first
    fields = dict(line.split(": ", 1) for line in lines if ": " in line)
    assert fields["sr.stat"].isdigit()  # a nested object as dotted keys
    assert float(fields["xvm"]) > 0


def test_send_json_prints_the_answer_as_json(idle: Daemon) -> None:
    result = idle.cli("send", MACHINE, '{"sr":null}', "--json")

    assert result.returncode == 0, result.stderr
    answer = json.loads(result.stdout)
    assert answer["status"] == 0 and "stat" in answer["r"]["sr"]


def test_send_of_a_gcode_line_moves_the_machine(idle: Daemon) -> None:
    result = idle.cli("send", MACHINE, "G90 G0 X3 Y4")

    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines() == ["ok"]
    snap = idle.wait_machine(lambda s: s["supervisor"] == "idle" and s["position"]["x"] == 3)
    assert snap["position"]["y"] == 4


def test_send_of_a_refused_line_fails_with_the_controllers_status(idle: Daemon) -> None:
    result = idle.cli("send", MACHINE, "G99")

    assert result.returncode == 1
    assert "1005" in result.stderr and "G99" in result.stderr
    assert result.stdout == ""


# -- run -------------------------------------------------------------------------


def test_run_follows_a_job_to_completion(completed: subprocess.CompletedProcess[str]) -> None:
    assert completed.returncode == 0, completed.stderr
    header, row = completed.stdout.splitlines()
    assert header.split()[:6] == ["JOB", "MACHINE", "KIND", "FILE", "STATE", "LINES"]
    assert row.split()[1:6] == [MACHINE, "make", "small.gcode", "completed", "5/5"]


def test_run_of_a_file_the_controller_rejects_fails(idle: Daemon, tmp_path: Path) -> None:
    path = tmp_path / "rejected.gcode"
    path.write_text(REJECTED, encoding="utf-8")

    result = idle.cli("run", str(path), "--machine", MACHINE)

    assert result.returncode == 1
    assert "failed" in result.stdout
    assert "failed" in result.stderr and "1005" in result.stderr


def test_run_on_an_unknown_machine_uploads_nothing(idle: Daemon, tmp_path: Path) -> None:
    path = tmp_path / "never.gcode"
    path.write_text(SMALL, encoding="utf-8")

    result = idle.cli("run", str(path), "--machine", "nope")

    assert result.returncode == 1 and "1001" in result.stderr
    assert "never.gcode" not in [f["name"] for f in idle.call("file.list")]


def start_long_job(daemon: Daemon, tmp_path: Path, program: str = LONG) -> Spawned:
    """`hostd run` of LONG, once the job has started (Ctrl-C is then a question)."""
    path = tmp_path / "long.gcode"
    path.write_text(program, encoding="utf-8")
    cli = daemon.spawn("run", str(path), "--machine", MACHINE)
    cli.expect("started on")
    return cli


def test_ctrl_c_during_run_pauses_then_resumes(idle: Daemon, tmp_path: Path) -> None:
    cli = start_long_job(idle, tmp_path)

    cli.interrupt()
    cli.expect("pause, cancel or continue? [p/c/Enter]")
    cli.answer("p")
    cli.expect("resume, cancel or stay paused? [r/c/Enter]")
    snap = idle.call("machine.status", machine=MACHINE)
    assert (snap["supervisor"], snap["job"]["state"]) == ("paused", "paused")
    cli.answer("r")

    status, out, _ = cli.finish()
    assert status == 0
    assert "completed" in out


def test_ctrl_c_during_run_cancels(idle: Daemon, tmp_path: Path) -> None:
    cli = start_long_job(idle, tmp_path, ENDLESS)

    cli.interrupt()
    cli.expect("[p/c/Enter]")
    cli.answer("c")

    status, out, err = cli.finish()
    assert status == 1
    assert "cancelled" in out and "cancelled" in err


def test_ctrl_c_with_no_one_to_answer_stops_following_and_leaves_the_job(
    idle: Daemon, tmp_path: Path
) -> None:
    cli = start_long_job(idle, tmp_path, ENDLESS)
    assert cli.process.stdin is not None
    cli.process.stdin.close()

    cli.interrupt()
    status, _, err = cli.finish()

    assert status == 130
    assert f"hostd cancel {MACHINE}" in err
    assert idle.call("machine.status", machine=MACHINE)["job"]["state"] == "running"
    cancelled = idle.cli("cancel", MACHINE)
    assert cancelled.returncode == 0, cancelled.stderr
    assert "cancelled" in cancelled.stdout


# -- lists -------------------------------------------------------------------------


def test_jobs_lists_the_job_run_left(
    idle: Daemon, completed: subprocess.CompletedProcess[str]
) -> None:
    table = idle.cli("jobs", "--machine", MACHINE, "--limit", "50")
    raw = idle.cli("--json", "jobs", "--limit", "50")

    assert table.returncode == 0 and raw.returncode == 0, table.stderr + raw.stderr
    assert any("small.gcode" in line and "completed" in line for line in table.stdout.splitlines())
    rows = json.loads(raw.stdout)
    small = [job for job in rows if job["file"] == "small.gcode"]
    assert small and small[0]["state"] == "completed" and small[0]["lines_acked"] == 5
    # MACHINE as every other command takes it, the same table.
    assert idle.cli("jobs", MACHINE, "--limit", "50").stdout == table.stdout
    other = idle.cli("jobs", "nope")
    assert other.returncode == 1 and "1001" in other.stderr  # that machine's, not all
    both = idle.cli("jobs", MACHINE, "--machine", "nope")
    assert both.returncode != 0 and "two machines" in both.stderr


def test_faults_of_a_healthy_machine_is_an_empty_list(idle: Daemon) -> None:
    table = idle.cli("faults", MACHINE)
    raw = idle.cli("faults", MACHINE, "--json")

    assert table.returncode == 0 and "no active faults" in table.stderr
    assert raw.returncode == 0 and json.loads(raw.stdout) == []
    whole = idle.cli("faults", MACHINE, "--all", "--json")
    assert whole.returncode == 0
    faults = json.loads(whole.stdout)
    assert len(faults) == 10 and not any(f["active"] for f in faults)


def test_a_fault_is_cleared_or_overridden_from_the_cli(idle: Daemon) -> None:
    def table() -> dict[str, dict[str, object]]:
        listed = idle.cli("faults", MACHINE, "--all", "--json")
        assert listed.returncode == 0, listed.stderr
        return {f["id"]: f for f in json.loads(listed.stdout)}

    try:
        assert idle.cli("faults", MACHINE, "--override", "water_flow").returncode == 0
        assert table()["water_flow"]["overridden"] is True
        assert idle.cli("faults", MACHINE, "--remove-override", "water_flow").returncode == 0
        assert table()["water_flow"]["overridden"] is False
    finally:
        idle.call("fault.override", machine=MACHINE, fault="water_flow", override=False)
    cleared = idle.cli("faults", MACHINE, "--all", "--clear", "serial")
    assert cleared.returncode == 0, cleared.stderr
    # The table says how each ends, as the command that ends it.
    rows = {line.split()[0]: line for line in cleared.stdout.splitlines()[1:] if line.strip()}
    assert "--clear" in rows["serial"] and "hostd reset" in rows["syntax"], cleared.stdout
    assert "its condition" in rows["lid_open"], cleared.stdout
    refused = idle.cli("faults", MACHINE, "--clear", "lid_open")
    assert refused.returncode == 1 and "condition goes away" in refused.stderr, refused.stderr
    refused = idle.cli("faults", MACHINE, "--override", "serial")
    assert refused.returncode == 1 and "cannot be overridden" in refused.stderr
    both = idle.cli("faults", MACHINE, "--clear", "serial", "--override", "water_flow")
    assert both.returncode != 0 and "not allowed with" in both.stderr


# -- machine actions -------------------------------------------------------------------


def test_hold_stops_a_move_and_resume_finishes_it(idle: Daemon) -> None:
    # ~6 s here: long enough that the hold's own process start cannot outlast the move
    # (2.4 s did not at load average 17: the move had ended when `hostd hold` connected).
    assert idle.cli("send", MACHINE, "G90 G1 X60 F60").returncode == 0

    held = idle.cli("hold", MACHINE)
    assert held.returncode == 0, held.stderr
    snap = idle.wait_machine(lambda s: s["state"]["name"] == "HOLD")
    assert snap["position"]["x"] < 60

    resumed = idle.cli("resume", MACHINE)
    assert resumed.returncode == 0, resumed.stderr
    idle.wait_machine(lambda s: s["supervisor"] == "idle" and s["position"]["x"] == 60, timeout=30)


def test_status_in_an_alarm_says_the_lockout_and_the_command_that_ends_it(idle: Daemon) -> None:
    """An ALARM never reads as all well: the lockout row names it and `hostd clear`, and
    the fault table's "normal" says it is the faults' only."""
    idle.call("machine.alarm", machine=MACHINE)
    idle.wait_machine(lambda s: s["lockout"] is not None)
    try:
        result = idle.cli("status", MACHINE)
        assert result.returncode == 0, result.stderr
        fields = dict(line.split(None, 1) for line in result.stdout.splitlines() if " " in line)
        assert (
            fields["lockout"].startswith("ALARM")
            and "(to end it: hostd clear)" in fields["lockout"]
        )
        assert fields["indicator"] == "normal (faults only)"
    finally:
        assert idle.cli("clear", MACHINE).returncode == 0
    idle.wait_machine(lambda s: s["lockout"] is None)
    fields = dict(line.split(None, 1) for line in idle.cli("status", MACHINE).stdout.splitlines())
    assert fields["lockout"] == "none" and fields["indicator"] == "normal"


def test_clear_outside_an_alarm_does_nothing(idle: Daemon) -> None:
    result = idle.cli("clear", MACHINE)

    assert result.returncode == 0, result.stderr
    assert idle.call("machine.status", machine=MACHINE)["supervisor"] == "idle"


def test_cancel_without_a_job_is_refused(idle: Daemon) -> None:
    result = idle.cli("cancel", MACHINE)

    assert result.returncode == 1 and "1003" in result.stderr


# -- watch -----------------------------------------------------------------------------


def test_watch_shows_status_as_the_machine_moves_until_ctrl_c(idle: Daemon) -> None:
    cli = idle.spawn("watch", MACHINE)
    cli.expect(f"{MACHINE} now idle", stream="out")

    assert idle.cli("send", MACHINE, "G90 G0 X8").returncode == 0
    line = cli.expect(f"{MACHINE} status", stream="out")
    cli.interrupt()

    status, _, err = cli.finish()
    assert status == 0, err
    assert "x=" in line


# -- reaching the daemon -------------------------------------------------------------------


def test_a_wrong_socket_path_is_exit_3_with_a_clear_message(daemon: Daemon, tmp_path: Path) -> None:
    missing = tmp_path / "nowhere.sock"

    result = daemon.cli("--socket", str(missing), "status")

    assert result.returncode == 3
    assert f"cannot reach hostd at {missing}" in result.stderr
    assert "is the daemon running?" in result.stderr


def test_bad_arguments_are_exit_2(daemon: Daemon) -> None:
    assert daemon.cli("send", MACHINE).returncode == 2
    assert daemon.cli("jobs", "--limit", "0").returncode == 2


def test_a_file_over_one_chunk_arrives_whole(daemon: Daemon) -> None:
    """Three `file.upload` pieces, only the last `final`: the daemon shows one whole file."""
    line = "G1 X1.000 Y1.000 F1200 (é)\n"
    text = line * (2 * UPLOAD_CHUNK // len(line) + 10)

    async def go(path: Path) -> int:
        async with Client(daemon.socket) as c:
            return await upload(c, path, "big.gcode")

    source = Path(daemon.log.parent / "big.gcode")
    source.write_text(text, encoding="utf-8")
    size = asyncio.run(go(source))

    assert size == len(text.encode())
    [listed] = [f for f in daemon.call("file.list") if f["name"] == "big.gcode"]
    assert listed["size"] == size


# -- analyze ---------------------------------------------------------------------------


def test_analyze_exits_1_when_job_start_would_refuse_the_file(idle: Daemon, tmp_path: Path) -> None:
    path = tmp_path / "tools.gcode"
    path.write_text("G21 G90\nT2 M6\nG0 X1\n", encoding="utf-8")

    refused = idle.cli("analyze", str(path), "--machine", MACHINE)

    assert refused.returncode == 1, refused.stderr
    assert "refused: line 2: M6 (tool change)" in refused.stdout
    assert refused.stdout.count("line 2: M6") == 1, refused.stdout  # said once, as refused
    assert "job.start refuses this file" in refused.stderr

    clean = tmp_path / "clean.gcode"
    clean.write_text(SMALL, encoding="utf-8")
    assert idle.cli("analyze", str(clean), "--machine", MACHINE).returncode == 0


def test_run_of_a_refused_file_says_why_and_force_runs_it(idle: Daemon, tmp_path: Path) -> None:
    path = tmp_path / "tools.gcode"
    path.write_text("G21 G90\nT2 M6\nG0 X1\nM2\n", encoding="utf-8")

    refused = idle.cli("run", str(path), "--machine", MACHINE)
    assert refused.returncode == 1 and "1008" in refused.stderr and "line 2" in refused.stderr

    forced = idle.cli("run", str(path), "--machine", MACHINE, "--force")
    assert forced.returncode == 0, forced.stderr
