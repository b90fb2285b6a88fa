"""Every docstring has a UTF-8 form, so each module imports on every Python hostd runs on.

Python 3.13 dedents a docstring as it compiles it, through UTF-8: a docstring that holds
a lone surrogate (a non-raw `"\\ud800"`, meant as JSON's escape) makes the import raise
UnicodeEncodeError. `hostd.api.rpc` had one, and the daemon did not start on 3.13
(Debian 13's). 3.11 and 3.12 keep such a docstring as it is, so the suite on them
cannot see it: this reads the source with `ast` instead.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("hostd", "bench", "tests")
_HAS_DOCSTRING = (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)


def surrogate_docstrings(source: str, name: str) -> list[str]:
    """Where a docstring of `source` has no UTF-8 form."""
    found = []
    for node in ast.walk(ast.parse(source, name)):
        if isinstance(node, _HAS_DOCSTRING):
            doc = ast.get_docstring(node, clean=False)
            if doc is not None:
                try:
                    doc.encode()
                except UnicodeEncodeError:
                    found.append(f"{name}:{getattr(node, 'lineno', 1)}")
    return found


def test_the_check_finds_a_lone_surrogate_and_lets_its_escape_by() -> None:
    assert surrogate_docstrings('def f():\n    """JSON\'s "\\ud800"."""\n', "x") == ["x:1"]
    assert surrogate_docstrings('"""JSON\'s "\\\\ud800"."""\n', "x") == []
    assert surrogate_docstrings('x = "\\ud800"\n', "x") == []  # data, not a docstring


def test_no_docstring_holds_a_lone_surrogate() -> None:
    found = [
        where
        for folder in FOLDERS
        for path in sorted((ROOT / folder).rglob("*.py"))
        for where in surrogate_docstrings(path.read_text(), str(path.relative_to(ROOT)))
    ]
    assert found == [], "write JSON's escape as \\\\ud800 in a docstring"
