"""How results read when they are not on a terminal (pure: no daemon)."""

from __future__ import annotations

import io

from rich.console import Console

from hostd.cli import render
from hostd.cli.progress import JobDisplay, RemainingColumn


def plain() -> tuple[Console, io.StringIO]:
    buffer = io.StringIO()
    return Console(file=buffer, width=40, force_terminal=False), buffer


def test_a_table_off_terminal_keeps_every_cell_whole_however_narrow() -> None:
    console, buffer = plain()
    long_error = "line 4: controller answered 131: Gcode command unsupported (1005)"

    render.table(console, ["JOB", "ERROR"], [["12", long_error], ["3", "-"]])

    assert buffer.getvalue().splitlines() == [
        "JOB  ERROR",
        f"12   {long_error}",
        "3    -",
    ]


def test_lines_is_acked_of_total_with_a_percentage() -> None:
    assert render.lines({"lines_acked": 3, "lines_total": 6}) == "3/6 (50%)"
    assert render.lines({"lines_acked": 0, "lines_total": 0}) == "0/0 (100%)"
    assert render.lines({"lines_acked": 2, "lines_total": None}) == "2"


def test_a_job_error_shows_its_message_and_code() -> None:
    job = {"error": {"code": 1005, "message": "controller answered 131"}}

    assert render.job_error(job) == "controller answered 131 (1005)"
    assert render.job_error({"error": None}) == "-"


def test_times_of_another_day_keep_their_date() -> None:
    assert render.when("2020-01-02T03:04:05.678Z").startswith("2020-01-0")
    assert render.when(None) == "-"


def test_a_send_answer_reads_as_status_then_key_value_lines() -> None:
    g2 = {"status": 0, "r": {"xvm": 16000, "sys": {"fv": 0.99, "fbs": "101.06"}, "x": None}}
    assert render.answer_lines(g2) == [
        "ok",
        "xvm: 16000",
        "sys.fv: 0.99",
        "sys.fbs: 101.06",
        "x: null",
    ]
    grbl = {"status": 0, "r": {"lines": ["$0=10", "[G54:0.000,0.000,0.000]"]}}
    assert render.answer_lines(grbl) == ["ok", "$0=10", "[G54:0.000,0.000,0.000]"]
    assert render.answer_lines({"status": 0, "r": {}}) == ["ok"]
    report = {"status": 0, "r": {"report": {"state": "Idle", "FS": [0, 0]}}}
    assert render.answer_lines(report) == ["ok", "report.state: Idle", "report.FS: [0,0]"]


def test_the_live_bar_says_finishing_once_every_line_is_answered_and_the_job_runs() -> None:
    """A job completes only when the board rests: its last answered lines may still be
    minutes of motion, which a countdown showed as 0:00:00."""
    buffer = io.StringIO()
    console = Console(file=buffer, width=120, force_terminal=True)
    job = {"id": 7, "file": "long.nc", "state": "running", "lines_total": 3, "lines_acked": 0}
    display = JobDisplay(console, job)
    progress = display._progress
    assert progress is not None  # a terminal: the live bar
    column = next(c for c in progress.columns if isinstance(c, RemainingColumn))

    def remaining() -> str:
        return column.render(progress.tasks[0]).plain

    display.update({**job, "lines_acked": 2}, "RUN")
    assert remaining() != "finishing"
    display.update({**job, "lines_acked": 3}, "RUN")
    assert remaining() == "finishing"
    display.update({**job, "lines_acked": 3, "state": "completed"}, "STOP")
    assert remaining() != "finishing"


def test_the_live_bar_says_the_line_the_board_runs() -> None:
    """Lines answered are only planned: the bar also says where the board is."""
    console = Console(file=io.StringIO(), width=120, force_terminal=True)
    job = {"id": 7, "file": "long.nc", "state": "running", "lines_total": 300, "lines_acked": 90}
    display = JobDisplay(console, job)
    progress = display._progress
    assert progress is not None
    display.update({**job, "line_executed": 41}, "RUN")
    assert progress.tasks[0].fields["where"] == "RUN · line 41"
    display.update({**job, "line_executed": None}, "RUN")  # a board that never says
    assert progress.tasks[0].fields["where"] == "RUN"


def test_a_machine_in_a_lockout_says_it_and_how_to_end_it_in_commands() -> None:
    """An ALARM is never read as all well: the lockout's cause and the commands that end
    it, and the fault table's "normal" said to be the faults' only."""
    console, buffer = plain()
    console.width = 200
    snap = {
        "id": "hal",
        "dialect": "grbl",
        "state": {"code": 2, "name": "ALARM"},
        "indicator": "normal",
        "lockout": {
            "state": "ALARM",
            "message": "Homing fail. Could not find limit switch within search distances.",
            "clear": "machine.clear or machine.home",
        },
    }

    render.snapshot(console, snap)

    fields = dict(line.split(None, 1) for line in buffer.getvalue().splitlines())
    assert fields["lockout"] == (
        "ALARM: Homing fail. Could not find limit switch within search distances. "
        "(to end it: hostd clear or hostd home)"
    )
    assert fields["indicator"] == "normal (faults only)"
    for state, message, clear, said in (
        ("ALARM", "alarm", "machine.reset, then machine.clear", "hostd reset, then hostd clear"),
        (
            "INTERLOCK",
            "",
            "close the interlock, then machine.cycle_start",
            "close the interlock, then hostd resume",
        ),
    ):
        lock = {"state": state, "message": message, "clear": clear}
        assert render.lockout({"lockout": lock}) == f"{state} (to end it: {said})"
    assert render.lockout({"lockout": None}) == "none"
    assert render.indicator({"indicator": "alert", "lockout": None}) == "alert"


def test_a_machine_connecting_to_a_busy_board_says_so_in_commands() -> None:
    """`hostd status` while the link waits on a board busy with moves of before: a
    `connecting` row with what the board does and the commands that end it."""
    console, buffer = plain()
    console.width = 300
    message = (
        "hal is Hold, busy with moves it was given before this connection: hostd "
        "connects once they end. machine.feedhold holds it; machine.reset empties it"
    )
    snap = {
        "id": "hal",
        "dialect": "grbl",
        "supervisor": "disconnected",
        "state": {"code": 6, "name": "HOLD"},
        "occupied": {"state": "Hold", "message": message},
    }
    render.snapshot(console, snap)
    fields = dict(line.split(None, 1) for line in buffer.getvalue().splitlines())
    assert fields["connecting"] == message.replace("machine.feedhold", "hostd hold").replace(
        "machine.reset", "hostd reset"
    )
    console, buffer = plain()
    render.snapshot(console, {**snap, "occupied": None})
    assert "connecting" not in buffer.getvalue()


def test_a_machine_waiting_for_a_tool_change_says_which_tool_and_how_to_go_on() -> None:
    console, buffer = plain()
    console.width = 200
    snap = {"id": "hal", "tool": 1, "tool_change": {"tool": 2, "line": 6}, "lockout": None}

    render.snapshot(console, snap)

    rows = dict(line.split("  ", 1) for line in buffer.getvalue().splitlines())
    rows = {k.strip(): v.strip() for k, v in rows.items()}
    assert rows["tool"] == "T1"
    assert (
        rows["tool change"]
        == "waiting for T2 at line 6 (once it is in: hostd tool-change-done hal)"
    )
    console, buffer = plain()
    render.snapshot(console, {"id": "hal", "tool": None, "tool_change": None})
    assert "tool change" not in buffer.getvalue()


def test_the_position_says_the_units_the_board_reports_it_in() -> None:
    """A grbl left in G20 still reports mm (only `$13` changes that): the row says mm."""
    grbl_g20 = {"position": {"x": 1.0}, "units": "in", "position_units": {"work": "mm"}}
    assert render.position(grbl_g20["position"], render.work_units(grbl_g20)) == "x=1.000 mm"
    older = {"position": {"x": 1.0}, "units": "in"}  # a daemon before position_units
    assert render.work_units(older) == "in"


def test_the_spindle_and_the_overrides_are_said_as_the_board_reports_them() -> None:
    console, buffer = plain()
    console.width = 200
    snap = {
        "id": "mill",
        "spindle": {"state": "ccw", "speed": 12000.0},
        "overrides": {"feed": 120, "spindle": 100, "rapid": 25},
    }

    render.snapshot(console, snap)

    rows = dict(line.split("  ", 1) for line in buffer.getvalue().splitlines())
    rows = {k.strip(): v.strip() for k, v in rows.items()}
    assert rows["spindle"] == "ccw, S12000"
    assert rows["overrides"] == "feed 120%, spindle 100%, rapid 25%"
    assert render.spindle({"state": "off", "speed": 12000.0}) == "off"  # the S kept is moot
    assert render.spindle({"state": None, "speed": None}) == render.spindle(None) == "-"
    assert render.overrides(None) == "-"
