"""Sample the daemon with py-spy (attached by pid, the daemon is not changed) and summarise.

py-spy comes with the `bench` extra (`pip install -e '.[bench]'`, which
`make bench` installs): it is found beside the interpreter, else on PATH, or
pass its path with `python -m bench --profile PATH`.
The raw output (collapsed stacks) is summarised as the functions that hold
the most samples themselves (self) and including what they call (total).
"""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

IDLE_LEAVES = ("EpollSelector.select", "select (selectors.py)")
# Frames under every stack of the event loop: left out of the "total" list.
BOILERPLATE = (
    "(<frozen runpy>)",
    "(asyncio/runners.py)",
    "BaseEventLoop.run_forever ",
    "BaseEventLoop.run_until_complete ",
    "BaseEventLoop._run_once ",
    "Handle._run ",
    "<module> ",
    "serve_main ",
)


@dataclass
class Profile:
    samples: int  # busy samples: the event loop waiting in epoll is counted apart
    idle: int
    own: list[tuple[str, int]]
    total: list[tuple[str, int]]
    path: Path


def find_py_spy(hint: str | None) -> str | None:
    if hint and hint != "auto":
        return hint
    # The `bench` extra installs it beside the interpreter (.venv/bin), which need not be on PATH.
    beside = Path(sys.executable).with_name("py-spy")
    return str(beside) if beside.exists() else shutil.which("py-spy")


def start(py_spy: str, pid: int, out: Path, rate: int = 500) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [
            py_spy,
            "record",
            "--pid",
            str(pid),
            "--rate",
            str(rate),
            "--nonblocking",
            "--format",
            "raw",
            "--output",
            str(out),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )


def stop(recorder: subprocess.Popen[bytes]) -> str:
    """Stop sampling; py-spy writes its output on SIGINT (on SIGTERM it writes nothing)."""
    recorder.send_signal(signal.SIGINT)
    _, err = recorder.communicate(timeout=60)
    return err.decode(errors="replace")


def summarise(path: Path, top: int = 20) -> Profile:
    own: Counter[str] = Counter()
    total: Counter[str] = Counter()
    samples = idle = 0
    for line in path.read_text().splitlines():
        stack, _, count_text = line.rpartition(" ")
        if not stack or not count_text.isdigit():
            continue
        count = int(count_text)
        frames = [_short(f) for f in stack.split(";")]
        # py-spy puts the thread name first ("process 123:..." / "thread ...").
        frames = [f for f in frames if not f.startswith(("process ", "thread "))]
        if not frames:
            continue
        if frames[-1].startswith(IDLE_LEAVES):
            idle += count
            continue
        samples += count
        own[frames[-1]] += count
        for frame in set(frames):
            if not any(marker in frame for marker in BOILERPLATE):
                total[frame] += count
    return Profile(samples, idle, own.most_common(top), total.most_common(top), path)


def _short(frame: str) -> str:
    """`func (path/to/module.py:123)` -> `func (module.py:123)`, site-packages trimmed."""
    name, _, where = frame.partition(" (")
    if not where:
        return frame
    where = where.rstrip(")")
    file = where.rpartition(":")[0]
    for marker in ("/site-packages/", "/lib/python3.11/", "/work/main/"):
        if marker in file:
            file = file.split(marker, 1)[1]
            break
    return f"{name} ({file})"


def render(profile: Profile) -> str:
    n = max(profile.samples, 1)
    share = 100 * profile.samples / max(profile.samples + profile.idle, 1)
    lines = [
        f"py-spy: {profile.samples} busy samples ({share:.0f}% of all; the rest waiting in"
        f" epoll), raw stacks in {profile.path}; percentages of busy samples",
        "",
        "self:",
    ]
    lines += [f"  {100 * c / n:5.1f}%  {f}" for f, c in profile.own]
    lines += ["", "total (including callees; the event loop's own frames left out):"]
    lines += [f"  {100 * c / n:5.1f}%  {f}" for f, c in profile.total]
    return "\n".join(lines)
