"""`python -m bench.analyze`: how fast the modal model reads G-code (issue 14: >= 100,000 lines/s).

Not a daemon figure, so not a row of bench/run.py: the model is pure and runs in
the bench's own process. Two programs: a CAM-like job of straight moves, and one
of arcs (the slow path), each 200,000 lines; the best of three runs.
"""

from __future__ import annotations

import sys
import time

from hostd.protocol.gcodestate import G2CORE, analyze

TARGET = 100_000  # lines/s
LINES = 200_000


def _straight(n: int) -> list[str]:
    head = ["G21 G90 G17 G94", "T1 M6", "S12000 M3", "G0 X0 Y0 Z5", "G1 Z-1 F300"]
    return head + [f"G1 X{i % 300}.{i % 997:03d} Y{(i * 7) % 200}.5 F800" for i in range(n)]


def _arcs(n: int) -> list[str]:
    lines = ["G20 G90 G0 X0 Y0", "G1 F20"]
    for i in range(n // 2):
        lines.append(f"G2 X1 Y{i % 50 * 0.01:.3f} I0.5 J0 ; an arc")
        lines.append(f"G3 X0 Y0 R0.{5 + i % 4}")
    return lines


def measure(lines: list[str], repeats: int = 3) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        analyze(lines, G2CORE)
        best = min(best, time.perf_counter() - start)
    return len(lines) / best


def main() -> int:
    ok = True
    for name, lines in (("straight moves", _straight(LINES)), ("arcs", _arcs(LINES))):
        rate = measure(lines)
        ok = ok and rate >= TARGET
        verdict = "PASS" if rate >= TARGET else "FAIL"
        print(f"analyze {name}: {rate:,.0f} lines/s (target {TARGET:,}) {verdict}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
