"""The modal model against LinuxCNC's interpreter, line by line, on real programs.

For each file, rs274 prints its own modal state after the probed lines (every
line of the small files) and its canonical moves; the model reads the same file
in the LinuxCNC dialect, with rs274's start (position 0, offsets 0, G28/G30 homes
at 0). Everything the model knows must match; what it says it does not know
(None) is only allowed where the file cannot tell (after G43, after G28 with an
unknown home), and is counted.
"""

from __future__ import annotations

import fcntl
import math
import os
import pickle
from pathlib import Path

import pytest

from hostd.protocol.gcodestate import LINUXCNC, GcodeModel, ModalState
from hostd.protocol.gcodestate.analysis import analyze
from hostd.protocol.gcodestate.state import AXES, WCS
from tests.protocol import rs274

NCFILES = Path("/usr/share/linuxcnc/ncfiles")  # linuxcnc-uspace's example programs
SAMPLES = Path(__file__).parent / "gcode_samples"
ZERO = dict.fromkeys(AXES, 0.0)
START = {
    "start": ZERO,
    "offsets": {w: ZERO for w in WCS},
    "homes": {"G28": ZERO, "G30": ZERO},
}

# (file, what it exercises, probe every n-th line)
FILES = [
    (NCFILES / "cds.ngc", "inch, N words, R arcs, G43, M3 S", 1),
    (NCFILES / "tort.ngc", "arcs in G17 G18 G19 with I/J/K, helices, F per arc", 1),
    (NCFILES / "plasmatest.ngc", "a CAM post's plasma job: M06 T1, I/J arcs, M30", 1),
    (NCFILES / "3dtest.ngc", "inch, full circles with only I/J", 1),
    (NCFILES / "arcspiral.ngc", "1,000 R arcs in inches, modal G2", 7),
    (SAMPLES / "offsets.ngc", "G92 G92.1-3, G10 L2/L20, G54-G59.1, G53, G28/G30, G93/G95", 1),
    (SAMPLES / "inch.ngc", "inch, R arcs > 180 degrees, G92 in inches", 1),
    (SAMPLES / "tlo.ngc", "G43.1 with its value, G53 and G92 under it, G49", 1),
]
_MOTION = {0: "G0", 10: "G1", 20: "G2", 30: "G3", 800: "G80"}
_PLANE = {170: "G17", 180: "G18", 190: "G19"}


def _wcs(code: float) -> str:
    return WCS[[540, 550, 560, 570, 580, 590, 591, 592, 593].index(round(code))]


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[Path, tuple[rs274.Run, set[int]]]:
    """rs274's runs of FILES, made once per test run: under pytest-xdist the first worker
    to get here runs them (several seconds of CPU) and the others read its results."""
    rs274.binary()  # fails, with how to install it, when it is missing
    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base  # this run's
    with open(shared / "rs274-runs.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        done = shared / "rs274-runs.pickle"
        if done.exists():
            kept: dict[Path, tuple[rs274.Run, set[int]]] = pickle.loads(done.read_bytes())
            return kept
        out = {}
        for path, _, every in FILES:
            assert path.exists(), f"{path}: {rs274.INSTALL}"
            count = len(path.read_text().splitlines())
            probes = set(range(1, count + 1, every)) | {count - 1, count}
            out[path] = (rs274.run(path, probes, tmp_path_factory.mktemp(path.stem)), probes)
        done.write_bytes(pickle.dumps(out))
        return out


def _differences(state: ModalState, probe: rs274.Probe) -> list[str]:
    v = probe.values
    diffs = []

    def check(what: str, ours: object, theirs: object) -> None:
        if ours != theirs:
            diffs.append(f"{what}: model {ours!r}, rs274 {theirs!r}")

    def close(what: str, ours: float | None, theirs: float, tol: float = 1e-4) -> None:
        if ours is not None and abs(ours - theirs) > tol:
            diffs.append(f"{what}: model {ours!r}, rs274 {theirs!r}")

    check("units", state.units, "G21" if v["m"] else "G20")
    check("distance", state.distance, "G90" if v["abs"] else "G91")
    check("arc distance", state.arc_distance, "G90.1" if v["ijk"] else "G91.1")
    check("plane", state.plane, _PLANE[round(v["pl"])])
    check("wcs", state.wcs, _wcs(v["cs"]))
    check("motion", state.motion, _MOTION.get(round(v["mm"]), v["mm"]))
    mode = "G93" if v["inv"] else "G95" if v["upr"] else "G94"
    check("feed mode", state.feed_mode, mode)
    if mode != "G93":
        close("feed", state.feed or 0.0, v["f"])
    close("speed", state.speed or 0.0, v["rpm"])
    spindle = "M5" if not v["son"] else "M3" if v["cw"] else "M4"
    check("spindle", state.spindle, spindle)
    check("flood", state.flood, bool(v["fl"]))
    check("mist", state.mist, bool(v["mi"]))
    check("tool", state.tool or 0, round(v["t"]))
    for axis in AXES:
        close(f"work {axis}", state.work[axis], v[axis])
    for axis in AXES:
        close(f"{state.wcs} offset {axis}", state.wcs_offsets[state.wcs][axis], probe.g5x[axis])
        close(f"G92 {axis}", state.g92[axis], probe.g92[axis])
    return diffs


@pytest.mark.parametrize(("path", "what", "every"), FILES, ids=[f[0].name for f in FILES])
def test_modal_state_matches_rs274_after_every_probed_line(
    runs: dict[Path, tuple[rs274.Run, set[int]]], path: Path, what: str, every: int
) -> None:
    run, _ = runs[path]
    assert run.probes, f"rs274 printed no probe for {path}: {run.errors}"
    model = GcodeModel(LINUXCNC, **START)  # type: ignore[arg-type]
    unknown = 0
    compared = 0
    for text in path.read_text().splitlines():
        model.step(text)
        probe = run.probes.get(model.line)
        if probe is None:
            continue
        state = model.state()
        compared += 1
        unknown += sum(v is None for v in state.work.values())
        diffs = _differences(state, probe)
        assert not diffs, f"{path.name} line {model.line} ({text!r}): {diffs}"
    # rs274 stops at M2/M30: every probe before it was compared.
    assert compared == len(run.probes) > 0
    assert unknown <= compared  # at most about an axis a line (Z after G43 until it moves)


@pytest.mark.parametrize(("path", "what", "every"), FILES, ids=[f[0].name for f in FILES])
def test_bounds_match_rs274(
    runs: dict[Path, tuple[rs274.Run, set[int]]], path: Path, what: str, every: int
) -> None:
    run, _ = runs[path]
    analysis = analyze(path.read_text().splitlines(), LINUXCNC, **START)  # type: ignore[arg-type]
    assert analysis.arcs == run.arcs
    for axis, (lo, hi) in analysis.bounds.items():
        theirs = run.bounds[axis]
        # rs274 prints 4 decimals of the current unit; its arcs are sampled every 0.1 degree.
        tol = 3e-3
        assert math.isclose(lo, theirs[0], abs_tol=tol), (axis, lo, theirs)
        assert math.isclose(hi, theirs[1], abs_tol=tol), (axis, hi, theirs)
    moved = {a for a, (lo, hi) in run.bounds.items() if hi - lo > 1e-9}
    assert moved <= set(analysis.bounds)
