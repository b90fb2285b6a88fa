"""`make demo` at the foundation stage: stream a sample job to the simulated board.

It runs the real parts (the simulator on a pseudo-terminal pair, the link,
the codec and the line-mode sender) without the daemon, which arrives with
the next issues and will then take this demo over.
"""

from __future__ import annotations

import asyncio
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from hostd.link import LineReceived, Link, LinkLost
from hostd.logs import configure_logging
from hostd.machine.linemode import InFlight, LineModeSender
from hostd.protocol.commands import encode_line, encode_set
from hostd.protocol.messages import Banner, Message, Response, StatusReport
from hostd.protocol.parser import parse_line
from hostd.protocol.program import program_lines
from hostd.protocol.states import MachineState, state_from_code
from hostd.sim import SimConfig, SimController

SAMPLE = Path(__file__).with_name("sample.gcode")
SETTINGS: list[dict[str, Any]] = [
    {"ej": 1},
    {"jv": 4},
    {"si": 100},
    {"sr": {k: True for k in ("stat", "line", "posx", "posy", "posz", "vel")}},
]


class DemoError(Exception):
    pass


class Board:
    """Just enough of a machine model to show the job: reads the link, keeps the state."""

    def __init__(self, link: Link) -> None:
        self.link = link
        self.state: MachineState | None = None
        self.position = {"x": 0.0, "y": 0.0, "z": 0.0}

    async def next_messages(self) -> list[Message]:
        messages: list[Message] = []
        for event in await self.link.read():
            if isinstance(event, LinkLost):
                raise DemoError(f"link lost: {event.reason}")
            assert isinstance(event, LineReceived)
            msg = parse_line(event.line)
            self._apply(msg)
            messages.append(msg)
        return messages

    def _apply(self, msg: Message) -> None:
        fields = msg.fields if isinstance(msg, StatusReport) else None
        if isinstance(msg, Response):
            fields = msg.status_report
        if fields:
            self.state = state_from_code(fields.get("stat")) or self.state
            for axis in self.position:
                if isinstance(fields.get(f"pos{axis}"), int | float):
                    self.position[axis] = float(fields[f"pos{axis}"])

    async def wait_banner(self) -> Banner:
        async with asyncio.timeout(5):
            while True:
                for msg in await self.next_messages():
                    if isinstance(msg, Banner):
                        return msg

    async def ask(self, line: bytes) -> Response:
        """One line, outside any job: write it and wait for its answer."""
        self.link.write_line(line)
        async with asyncio.timeout(5):
            while True:
                for msg in await self.next_messages():
                    if isinstance(msg, Response):
                        if not msg.ok:
                            raise DemoError(f"{line!r} answered with status {msg.status}")
                        return msg


async def stream(board: Board, path: Path, console: Console) -> int:
    with path.open() as f:
        total = sum(1 for _ in program_lines(f))
    sender = LineModeSender(window=4)
    acked = 0
    started = time.monotonic()
    columns = (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.percentage:>3.0f}%  {task.fields[rate]:>5.0f} lines/s"),
        TimeRemainingColumn(),
        TextColumn("{task.fields[where]}"),
    )
    with path.open() as f, Progress(*columns, console=console) as progress:
        task = progress.add_task(path.name, total=total, rate=0.0, where="")
        lines = program_lines(f)
        pending = next(lines, None)
        while True:
            while pending is not None and sender.has_room:
                number, text = pending
                board.link.write_line(encode_line(text))
                sender.sent(InFlight(encode_line(text), file_line=number))
                pending = next(lines, None)
            for msg in await board.next_messages():
                if isinstance(msg, Response):
                    entry = sender.answered(msg)
                    if not msg.ok:
                        raise DemoError(f"line {entry.file_line} refused: status {msg.status}")
                    acked += 1
            state = board.state.name if board.state is not None else "?"
            pos = board.position
            progress.update(
                task,
                completed=acked,
                rate=acked / max(time.monotonic() - started, 1e-6),
                where=f"{state:<12} X{pos['x']:8.3f} Y{pos['y']:8.3f}",
            )
            # {r} means queued, not done: the job ends when the board says so.
            finished = board.state in (MachineState.PROGRAM_STOP, MachineState.PROGRAM_END)
            if pending is None and not len(sender) and finished:
                return acked


async def run(console: Console) -> int:
    config = SimConfig(speed_factor=40.0, status_interval=0.1)
    with tempfile.TemporaryDirectory(prefix="hostd-demo-") as tmp:
        async with SimController(str(Path(tmp) / "ttyG2"), config=config) as sim:
            console.print(f"simulated g2core on [bold]{sim.data_path}[/bold]")
            link = await Link.open(sim.data_path)
            try:
                board = Board(link)
                banner = await board.wait_banner()
                console.print(f"board says SYSTEM READY: firmware build {banner.fb}")
                for setting in SETTINGS:
                    await board.ask(encode_set(setting))
                console.print(f"settings sent ({len(SETTINGS)} lines), streaming {SAMPLE.name}")
                acked = await stream(board, SAMPLE, console)
                state = board.state.name if board.state else "?"
                console.print(f"[green]job complete[/green]: {acked} lines answered, board {state}")
            finally:
                await link.close()
    return 0


def main() -> int:
    configure_logging("warning")
    console = Console()
    try:
        return asyncio.run(run(console))
    except (DemoError, TimeoutError) as exc:
        console.print(f"[red]demo failed[/red]: {exc or 'timed out'}")
        return 1


if __name__ == "__main__":
    sys.exit(main())
