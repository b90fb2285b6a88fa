"""`hostd run` at a tool change: the prompt, answered by Enter or by `hostd tool-change-done`.

A real `hostd serve` with the simulated g2core, `tool_change = "pause"`.
"""

from __future__ import annotations

from pathlib import Path

from tests.cli.conftest import MACHINE, Daemon

EXTRA_CONFIG = 'tool_change = "pause"\n'  # in the machine's table (conftest's EXTRA_CONFIG)
TWO_TOOLS = "G21 G90\nG0 X0 Y0 Z0\nT1 M6\nG0 X1\nG1 X2 F3000\nT2 M6\nG0 X3\nM2\n"


def _file(tmp_path: Path) -> str:
    path = tmp_path / "two-tools.nc"
    path.write_text(TWO_TOOLS, encoding="utf-8")
    return str(path)


def test_run_prompts_at_each_tool_change_and_enter_goes_on(idle: Daemon, tmp_path: Path) -> None:
    cli = idle.spawn("run", _file(tmp_path), "--machine", MACHINE)
    cli.expect("Change to tool 1 (line 3), then press Enter")
    assert idle.call("machine.status", machine=MACHINE)["tool_change"] == {"tool": 1, "line": 3}
    cli.answer("")
    cli.expect("Change to tool 2 (line 6), then press Enter")
    cli.answer("")

    status, out, err = cli.finish()
    assert status == 0, err
    assert "completed" in out
    job = idle.call("job.list", machine=MACHINE, limit=1)[0]
    assert [(c["tool"], c["line"]) for c in job["tool_changes"]] == [(1, 3), (2, 6)]


def test_without_input_run_says_how_to_answer_and_waits(idle: Daemon, tmp_path: Path) -> None:
    cli = idle.spawn("run", _file(tmp_path), "--machine", MACHINE)
    assert cli.process.stdin is not None
    cli.process.stdin.close()  # nobody at the keyboard: a script, a service
    cli.expect(f"then answer with `hostd tool-change-done {MACHINE}`")
    status = idle.cli("status", MACHINE).stdout
    assert (
        f"waiting for T1 at line 3 (once it is in: hostd tool-change-done {MACHINE})" in status
    ), status
    answered = idle.cli("tool-change-done", MACHINE)
    assert answered.returncode == 0, answered.stderr
    assert "two-tools.nc" in answered.stdout
    cli.expect("Change to tool 2 (line 6), then answer with")
    status = idle.cli("status", MACHINE).stdout
    assert "waiting for T2 at line 6" in status, status
    tool = [line for line in status.splitlines() if line.split()[:1] == ["tool"]]
    assert tool and tool[0].split()[1] == "T1", status  # the one put in at line 3
    assert idle.cli("tool-change-done", MACHINE).returncode == 0

    status, out, err = cli.finish()
    assert status == 0, err
    assert "completed" in out


def test_tool_change_done_with_nothing_waiting_is_refused(idle: Daemon) -> None:
    refused = idle.cli("tool-change-done", MACHINE)
    assert refused.returncode != 0
    assert "not waiting for a tool change" in refused.stderr
