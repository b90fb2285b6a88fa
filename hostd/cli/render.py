"""How the CLI shows api.md's objects: snapshots, job rows, faults.

Two renderings of the same rows: a rich table on a terminal, and plain
space-aligned columns otherwise. Rich sizes tables to the terminal (80
columns when there is none) and would wrap or truncate cells in a pipe;
scripts and logs want every value whole, one row per line.

Every function here is pure apart from printing to the console it is given,
so the formats can be checked without a daemon.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from rich import box
from rich.console import Console
from rich.table import Table

NONE = "-"


@dataclass(frozen=True, slots=True)
class Output:
    """Where results go (`out`, stdout) and where messages go (`err`, stderr)."""

    out: Console
    err: Console
    json: bool = False

    def print_json(self, value: Any) -> None:
        """One compact JSON document per line: what scripts parse."""
        self.out.print(json_line(value), markup=False, highlight=False, soft_wrap=True)

    def result(self, value: Any, text: str) -> None:
        """A command's result: the JSON with `--json`, else one line saying what happened."""
        if self.json:
            self.print_json(value)
        else:
            self.out.print(text, markup=False, highlight=False)

    def message(self, text: str) -> None:
        """A line for the user that is not the result (progress notes, confirmations)."""
        self.err.print(text, markup=False, highlight=False, soft_wrap=True)


def make_output(*, json_output: bool) -> Output:
    return Output(
        out=Console(highlight=False, soft_wrap=False),
        err=Console(stderr=True, highlight=False),
        json=json_output,
    )


def json_line(value: Any) -> str:
    return json.dumps(value, separators=(",", ":"), ensure_ascii=False)


def table(console: Console, headers: Sequence[str], rows: Sequence[Sequence[str]]) -> None:
    """Rows under headers: a rich table when it fits the terminal, aligned plain text otherwise.

    A rich table squeezed into a narrow terminal folds cells a character wide
    at a time; plain lines that the terminal wraps stay readable.
    """
    widths = [len(h) for h in headers]
    for row in rows:
        widths = [max(w, len(cell)) for w, cell in zip(widths, row, strict=True)]
    natural = sum(widths) + 3 * (len(widths) - 1)
    if console.is_terminal and natural <= console.width:
        grid = Table(box=box.SIMPLE_HEAD, show_edge=False, pad_edge=False)
        for header in headers:
            grid.add_column(header, no_wrap=True)
        for row in rows:
            grid.add_row(*row)
        console.print(grid)
        return
    for i, line in enumerate([list(headers), *rows]):
        text = "  ".join(cell.ljust(w) for cell, w in zip(line, widths, strict=True)).rstrip()
        style = "bold" if i == 0 and console.is_terminal else None
        console.print(text, markup=False, highlight=False, soft_wrap=True, style=style)


def pairs(console: Console, items: Sequence[tuple[str, str]]) -> None:
    """A readable key/value listing (one machine's snapshot)."""
    width = max((len(k) for k, _ in items), default=0)
    for key, value in items:
        if console.is_terminal:
            console.print(f"[bold]{key.ljust(width)}[/bold]  ", end="")
            console.print(value, markup=False, highlight=False, soft_wrap=True)
        else:
            console.print(f"{key.ljust(width)}  {value}", markup=False, soft_wrap=True)


# -- cells -----------------------------------------------------------------


def position(pos: Any, units: Any = None) -> str:
    if not isinstance(pos, dict) or not pos:
        return NONE
    text = " ".join(f"{axis}={_num(value)}" for axis, value in pos.items())
    return f"{text} {units}" if isinstance(units, str) else text


def work_units(snapshot: dict[str, Any]) -> Any:
    """What the work position is in (`position_units`; before it, the units mode): a grbl
    in G20 still reports mm, unless its `$13` says inches."""
    units = snapshot.get("position_units")
    return units.get("work") if isinstance(units, dict) else snapshot.get("units")


def state_name(snapshot: dict[str, Any]) -> str:
    state = snapshot.get("state")
    if isinstance(state, dict):
        return str(state.get("name", NONE))
    return NONE


# The API's words for what ends a lockout (docs/api.md, "The lockout in the snapshot"),
# as the commands that say them here.
_CLI_WORDS = {
    "machine.clear": "hostd clear",
    "machine.home": "hostd home",
    "machine.reset": "hostd reset",
    "machine.cycle_start": "hostd resume",
    "machine.feedhold": "hostd hold",
}
_API_METHOD = re.compile(r"machine\.\w+")


def lockout(snapshot: dict[str, Any]) -> str:
    """`ALARM: what caused it (to end it: hostd clear or hostd home)`, or `none`."""
    lock = snapshot.get("lockout")
    if not isinstance(lock, dict):
        return "none"
    state, message = str(lock.get("state")), str(lock.get("message") or "")
    clear = _API_METHOD.sub(lambda m: _CLI_WORDS.get(m[0], m[0]), str(lock.get("clear") or ""))
    text = state if message.lower() in ("", state.lower()) else f"{state}: {message}"
    return f"{text} (to end it: {clear})" if clear else text


def _occupied(snapshot: dict[str, Any]) -> list[tuple[str, str]]:
    """A row while the link waits on a board busy with moves of before (docs/api.md)."""
    busy = snapshot.get("occupied")
    if not isinstance(busy, dict):
        return []
    message = _API_METHOD.sub(lambda m: _CLI_WORDS.get(m[0], m[0]), str(busy.get("message")))
    return [("connecting", message)]


def _tool_change(snapshot: dict[str, Any]) -> list[tuple[str, str]]:
    """A row while a job waits for a tool change: which tool, and how to go on."""
    wait = snapshot.get("tool_change")
    if not isinstance(wait, dict):
        return []
    line = f" at line {wait['line']}" if isinstance(wait.get("line"), int) else ""
    return [
        (
            "tool change",
            f"waiting for T{wait.get('tool')}{line} "
            f"(once it is in: hostd tool-change-done {snapshot.get('id')})",
        )
    ]


def indicator(snapshot: dict[str, Any]) -> str:
    """The fault table's light (behaviour.md). A controller lockout is not a fault: beside
    one, a bare "normal" would read as all well, so it says whose light it is."""
    text = str(snapshot.get("indicator"))
    return f"{text} (faults only)" if isinstance(snapshot.get("lockout"), dict) else text


def lines(job: dict[str, Any]) -> str:
    """`acked/total (pct%)`: what the controller has answered, of what the file holds."""
    acked = job.get("lines_acked") or 0
    total = job.get("lines_total")
    if not isinstance(total, int):
        return str(acked)
    pct = 100.0 if total == 0 else 100.0 * acked / total
    return f"{acked}/{total} ({pct:.0f}%)"


def job_brief(job: Any) -> str:
    """The job column of the status table: which job, in which state, how far."""
    if not isinstance(job, dict):
        return NONE
    return f"#{job.get('id')} {job.get('state')} {lines(job)}"


def job_error(job: dict[str, Any]) -> str:
    error = job.get("error")
    if not isinstance(error, dict):
        return NONE
    return f"{error.get('message')} ({error.get('code')})"


def when(stamp: Any) -> str:
    """An api.md ISO 8601 UTC time in the reader's local time, to the second (today: no date)."""
    if not isinstance(stamp, str):
        return NONE
    try:
        parsed = datetime.fromisoformat(stamp.replace("Z", "+00:00"))
    except ValueError:
        return stamp
    local = parsed.astimezone()
    if local.date() == datetime.now().astimezone().date():
        return local.strftime("%H:%M:%S")  # today's: the date would only take room
    return local.strftime("%Y-%m-%d %H:%M:%S")


def spindle(value: Any) -> str:
    """The snapshot's `spindle` as the board reported it: "cw, S12000", "off", or "-"."""
    if not isinstance(value, dict) or value.get("state") is None:
        return NONE
    speed = value.get("speed")
    if value["state"] == "off" or not isinstance(speed, float | int):
        return str(value["state"])
    return f"{value['state']}, S{speed:g}"


def overrides(value: Any) -> str:
    """The snapshot's `overrides` (percent): "feed 120%, spindle 100%, rapid 25%", or "-"."""
    if not isinstance(value, dict):
        return NONE
    shown = [f"{k} {value[k]:g}%" for k in ("feed", "spindle", "rapid") if value.get(k) is not None]
    return ", ".join(shown) or NONE


def _num(value: Any) -> str:
    if isinstance(value, float | int) and not isinstance(value, bool):
        return f"{value:.3f}"
    return str(value)


def _yes_no(value: Any) -> str:
    if value is None:
        return "unknown"
    return "yes" if value else "no"


# -- whole objects -----------------------------------------------------------


JOB_HEADERS = ("JOB", "MACHINE", "KIND", "FILE", "STATE", "LINES", "STARTED", "ENDED", "ERROR")


def job_row(job: dict[str, Any]) -> list[str]:
    return [
        str(job.get("id")),
        str(job.get("machine")),
        str(job.get("kind")),
        str(job.get("file") or NONE),
        str(job.get("state")),
        lines(job),
        when(job.get("started_at")),
        when(job.get("ended_at")),
        job_error(job),
    ]


def jobs(console: Console, rows: Sequence[dict[str, Any]]) -> None:
    table(console, JOB_HEADERS, [job_row(job) for job in rows])


STATUS_HEADERS = ("MACHINE", "SUPERVISOR", "STATE", "POSITION", "JOB")


def status_row(snapshot: dict[str, Any]) -> list[str]:
    return [
        str(snapshot.get("id")),
        str(snapshot.get("supervisor")),
        state_name(snapshot),
        position(snapshot.get("position")),
        job_brief(snapshot.get("job")),
    ]


def machines(console: Console, snapshots: Sequence[dict[str, Any]]) -> None:
    table(console, STATUS_HEADERS, [status_row(s) for s in snapshots])


def snapshot(console: Console, snap: dict[str, Any]) -> None:
    """One machine, every field of api.md's snapshot in words."""
    state = snap.get("state")
    code = f" ({state.get('code')})" if isinstance(state, dict) else ""
    faults = snap.get("faults") or []
    fault_text = (
        ", ".join(f"{f.get('id')} ({f.get('severity')})" for f in faults) if faults else "none"
    )
    exception = snap.get("last_exception")
    pairs(
        console,
        [
            ("machine", f"{snap.get('id')} ({snap.get('dialect')})"),
            ("supervisor", str(snap.get("supervisor"))),
            *_occupied(snap),
            ("state", state_name(snap) + code),
            ("lockout", lockout(snap)),
            ("position", position(snap.get("position"), work_units(snap))),
            ("line", str(snap.get("line") if snap.get("line") is not None else NONE)),
            ("velocity", _num(snap.get("velocity")) if snap.get("velocity") is not None else NONE),
            ("feed", _num(snap.get("feed")) if snap.get("feed") is not None else NONE),
            ("homed", _yes_no(snap.get("homed"))),
            ("tool", f"T{snap['tool']}" if isinstance(snap.get("tool"), int) else NONE),
            *_tool_change(snap),
            ("spindle", spindle(snap.get("spindle"))),
            ("overrides", overrides(snap.get("overrides"))),
            ("indicator", indicator(snap)),
            ("faults", fault_text),
            ("job", _job_long(snap.get("job"))),
            ("last exception", json_line(exception) if exception is not None else "none"),
        ],
    )


def _job_long(job: Any) -> str:
    if not isinstance(job, dict):
        return "none"
    text = f"#{job.get('id')} {job.get('kind')} {job.get('file') or ''} {job.get('state')}"
    text = " ".join(text.split()) + f", lines {lines(job)}"
    if isinstance(job.get("error"), dict):
        text += f", error: {job_error(job)}"
    return text


# How a fault ends (the fault object's `clears`), as the command that ends it.
_CLEARS = {"signal": "its condition", "software": "--clear", "reset": "hostd reset"}

FAULT_HEADERS = (
    "FAULT",
    "SEVERITY",
    "ACTIVE",
    "OVERRIDDEN",
    "OVERRIDABLE",
    "CLEARS",
    "SINCE",
    "VALUE",
    "MESSAGE",
)


def faults(console: Console, rows: Sequence[dict[str, Any]]) -> None:
    table(
        console,
        FAULT_HEADERS,
        [
            [
                str(f.get("id")),
                str(f.get("severity")),
                _yes_no(f.get("active")),
                _yes_no(f.get("overridden")),
                _yes_no(f.get("overridable")),
                _CLEARS.get(str(f.get("clears")), "-"),
                when(f.get("since")),
                json_line(f.get("value")),
                str(f.get("message") or ""),
            ]
            for f in rows
        ],
    )


def answer_lines(result: dict[str, Any]) -> list[str]:
    """machine.send's answer for a person: the status, then the body as `key: value` lines.

    Nested objects read as dotted keys (`sys.fv: 0.99`); the text a grbl board printed
    before its `ok` (`lines`) is shown as it printed it, one line each.
    """
    status = result.get("status")
    out = ["ok" if status == 0 else f"status {status}"]
    body = result.get("r")
    if isinstance(body, dict):
        out += [_pair(key, value) for key, value in _flat(body, "")]
    elif body is not None:
        out.append(_scalar(body))
    return out


def _flat(value: dict[str, Any], prefix: str) -> list[tuple[str, Any]]:
    pairs: list[tuple[str, Any]] = []
    for key, item in value.items():
        name = f"{prefix}{key}"
        if isinstance(item, dict) and item:
            pairs += _flat(item, f"{name}.")
        elif key == "lines" and not prefix and isinstance(item, list):
            pairs += [("", text) for text in item]
        else:
            pairs.append((name, item))
    return pairs


def _pair(key: str, value: Any) -> str:
    return _scalar(value) if key == "" else f"{key}: {_scalar(value)}"


def _scalar(value: Any) -> str:
    return value if isinstance(value, str) else json_line(value)
