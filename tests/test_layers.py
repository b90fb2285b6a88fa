"""No import runs back up a layer (docs/architecture.md; issue 28).

The layers, lowest first: protocol -> link -> machine -> api -> cli. `sim`
stands beside them and uses `protocol` only. The modules outside the
folders have a place too: `daemon.py` between `machine` and `api` (it holds
the machines the API serves); `config.py` above `api`, where the sections each
layer declares (machine/config.py, api/webconfig.py, ...) are assembled into
the config file, and below `cli`, which reads it; `service.py`, `__main__.py`,
`logs.py`, `notify.py` and `demo/` on top, putting it all together.

The source is read with `ast`, never imported, so nothing runs. Every
import counts: at module level, inside a function, under TYPE_CHECKING.
The back-arrows that exist today are listed in BENDS with the reason for
each (docs/architecture.md, "Where the layers bend"); a new one fails the
test, and so does a listed one that is gone, so the list only shrinks.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest

HOSTD = Path(__file__).resolve().parents[1] / "hostd"

ROOT = "hostd"  # the package itself (`__version__`): below everything
RANK: dict[str, float] = {
    ROOT: -1,
    "protocol": 0,
    "link": 1,
    "machine": 2,
    "daemon": 2.5,
    "api": 3,
    "config": 3.5,
    "cli": 4,
    **dict.fromkeys(("service", "__main__", "logs", "notify", "demo"), 9),
}
SIM = "sim"

# (importer, imported) -> why. Only shrinks: a listed arrow that is gone fails too.
BENDS: dict[tuple[str, str], str] = {}


def modules(root: Path) -> dict[str, Path]:
    """Every module under `root` (a package folder) by its dotted name."""
    found = {}
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root.parent).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        found[".".join(parts)] = path
    return found


def imports(name: str, path: Path, known: set[str]) -> set[str]:
    """The modules of the package that `name` imports, relative imports resolved."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    targets: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*up, *([base] if base else [])])
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                targets.add(sub if sub in known else base)  # `from hostd.api import rpc`
    top = name.split(".")[0]
    return {t for t in targets if t == top or t.startswith(top + ".")}


def unit(module: str) -> str:
    """The layer a module belongs to: its first folder, or the top-level module."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ROOT


def allowed(src: str, dst: str) -> bool:
    a, b = unit(src), unit(dst)
    if a == b or b == ROOT:
        return True
    if a == SIM:
        return b == "protocol"
    if b == SIM:
        return False
    for place in (a, b):
        if place not in RANK:
            pytest.fail(f"hostd/{place} has no place in the layers: add it to RANK (and the docs)")
    return RANK[b] <= RANK[a]


def back_arrows(root: Path) -> set[tuple[str, str]]:
    found = modules(root)
    known = set(found)
    return {
        (name, target)
        for name, path in found.items()
        for target in imports(name, path, known)
        if not allowed(name, target)
    }


@functools.cache
def hostd_arrows() -> frozenset[tuple[str, str]]:
    """hostd's own back-arrows, read once for the two tests below (about 1.5 s of CPU
    to parse every module; the source does not change while the suite runs)."""
    return frozenset(back_arrows(HOSTD))


def test_no_import_runs_back_up_a_layer() -> None:
    new = hostd_arrows() - set(BENDS)
    arrows = "\n".join(f"  {a} -> {b}" for a, b in sorted(new))
    assert not new, "imports back up a layer:\n" + arrows


def test_every_listed_bend_still_exists() -> None:
    gone = set(BENDS) - hostd_arrows()
    assert not gone, "no longer bends, remove from BENDS and docs/architecture.md: " + str(gone)


def test_the_walk_sees_every_kind_of_import(tmp_path: Path) -> None:
    """A planted tree: the checker finds an arrow however it is written, and only those."""
    pkg = tmp_path / "hostd"
    for folder in ("protocol", "link", "machine", "api", "sim"):
        (pkg / folder).mkdir(parents=True)
        (pkg / folder / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("__version__ = '0'\n")
    (pkg / "machine" / "engine.py").write_text("X = 1\n")
    (pkg / "api" / "rpc.py").write_text("from hostd import __version__\nimport hostd.machine\n")
    (pkg / "protocol" / "a.py").write_text("from ..machine import engine\n")
    (pkg / "protocol" / "b.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from hostd.api import rpc\n"
    )
    (pkg / "link" / "c.py").write_text("def f():\n    import hostd.machine.engine\n")
    (pkg / "sim" / "d.py").write_text("from hostd.protocol import a\nfrom hostd.link import c\n")
    (pkg / "machine" / "e.py").write_text("from hostd.sim import d\nfrom . import engine\n")
    assert back_arrows(pkg) == {
        ("hostd.protocol.a", "hostd.machine.engine"),
        ("hostd.protocol.b", "hostd.api.rpc"),
        ("hostd.link.c", "hostd.machine.engine"),
        ("hostd.sim.d", "hostd.link.c"),
        ("hostd.machine.e", "hostd.sim.d"),
    }
