"""PLANNER_STARTUP (planner.cpp mp_planner_callback): from rest, g2core plans before it moves.

The first move waits until the planner is full, or until no block has come
for BLOCK_TIMEOUT_MS (30 ms); a board already moving takes new blocks
without waiting. The board is driven by plain calls, with its clock in hand.
"""

from __future__ import annotations

from hostd.protocol.states import MachineState
from hostd.sim import SimConfig
from hostd.sim.board import BLOCK_TIMEOUT, Board
from hostd.sim.scanner import DataLine


class Bench:
    def __init__(self, planner_depth: int = 4) -> None:
        self.now = 0.0
        self.board = Board(
            SimConfig(planner_depth=planner_depth, status_interval=1.0),
            emit=lambda _line: None,
            clock=lambda: self.now,
            reset=lambda: None,
        )
        self.board.open_rx("data")

    def send(self, *lines: str) -> None:
        for line in lines:
            self.board.queue_line("data", DataLine(line.encode()))
        self.run()

    def run(self) -> None:
        while self.board.tick():
            pass

    def at(self, now: float) -> MachineState:
        self.now = now
        self.run()
        return self.board.state


def test_a_move_from_rest_waits_for_the_block_timeout() -> None:
    bench = Bench()
    bench.send("G1 X10 F600")  # one second of motion
    # The cycle starts as the move is parsed (stat RUN), the motion once the planner primed.
    assert bench.board.state is MachineState.RUN and bench.board.active is None
    deadline = bench.board.next_deadline()
    assert deadline is not None and abs(deadline - BLOCK_TIMEOUT) < 1e-9
    bench.at(BLOCK_TIMEOUT * 0.9)
    assert bench.board.active is None and bench.board.position["x"] == 0
    bench.at(BLOCK_TIMEOUT)
    assert bench.board.active is not None


def test_each_new_block_restarts_the_wait_and_a_full_planner_moves_at_once() -> None:
    bench = Bench(planner_depth=4)
    bench.send("G1 X1 F600")
    bench.at(0.02)
    bench.send("G1 X2")
    bench.at(0.04)
    assert bench.board.active is None  # 20 ms after the last block: still priming
    bench.send("G1 X3", "G1 X4")  # the planner is full: no reason to wait
    assert bench.board.active is not None


def test_a_moving_board_does_not_wait_for_new_blocks() -> None:
    bench = Bench(planner_depth=8)
    bench.send("G1 X1 F600")  # 0.1 s
    bench.at(BLOCK_TIMEOUT)
    bench.send("G1 X2")
    bench.at(BLOCK_TIMEOUT + 0.1)
    assert bench.board.active is not None  # straight on into the next, no new wait
    assert bench.at(BLOCK_TIMEOUT + 0.2) is MachineState.PROGRAM_STOP
    bench.send("G1 X3")  # from rest again: it primes again
    bench.at(BLOCK_TIMEOUT + 0.2 + BLOCK_TIMEOUT * 0.5)
    assert bench.board.active is None and bench.board.state is MachineState.RUN
