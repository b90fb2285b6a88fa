"""The client subcommands of `hostd`: each one coroutine over a connected `Client`.

A command returns its exit status (0 success, 1 the daemon said no or the
job did not complete) and lets `RpcError` and the connection errors
propagate: `main.py` turns those into a message on stderr and the exit
status documented there, the same way for every command.

Results go to stdout (tables, or JSON with `--json`); progress and notes
go to stderr, so `hostd --json jobs | jq` never sees a progress bar.

One module per topic, as hostd/api/methods/: `base` (exit statuses, the
client-side error, following a job), `machine` (status, send, watch, the
one-shot actions), `lists` (jobs, faults), `files` (upload, run, analyze),
`operations` (the operator's day: home, zero, probe, override, spindle,
frame, laser test, macros). main.py finds each command here by its name.
"""

from __future__ import annotations

from hostd.cli.commands.base import FAILED, INTERRUPTED, OK, USAGE, CliError
from hostd.cli.commands.files import (
    MAX_TEXT_JSON,
    UPLOAD_CHUNK,
    analyze,
    confirm,
    resume_plan,
    run,
    upload,
    upload_chunks,
)
from hostd.cli.commands.lists import faults, jobs
from hostd.cli.commands.machine import (
    ACTIONS,
    action,
    cancel,
    send,
    status,
    tool_change_done,
    watch,
)
from hostd.cli.commands.operations import (
    AXIS_LETTERS,
    axis_letters,
    frame,
    home,
    laser_test,
    macro,
    override,
    probe,
    spindle,
    zero,
)

__all__ = [
    "ACTIONS",
    "AXIS_LETTERS",
    "FAILED",
    "INTERRUPTED",
    "MAX_TEXT_JSON",
    "OK",
    "UPLOAD_CHUNK",
    "USAGE",
    "CliError",
    "action",
    "analyze",
    "axis_letters",
    "cancel",
    "confirm",
    "faults",
    "frame",
    "home",
    "jobs",
    "laser_test",
    "macro",
    "override",
    "probe",
    "resume_plan",
    "run",
    "send",
    "spindle",
    "status",
    "tool_change_done",
    "upload",
    "upload_chunks",
    "watch",
    "zero",
]
