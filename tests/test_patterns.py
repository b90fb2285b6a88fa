"""No regular expression of hostd repeats a group possessively (`(?:...)*+`, `++`, `?+`).

CPython 3.11.0 to 3.11.4 match such a repeat wrongly when an iteration fails part
of the way in: the position is not put back where the last whole iteration ended
(python/cpython#100061 and #106052, fixed in 3.11.5). Debian 12 and Raspberry Pi OS
ship 3.11.2, and the service runs on it (docs/operations.md): there `read_words("X1
Y")` said the whole text was words, and a job line with a letter and no number was
not refused. An atomic group holding a greedy repeat, `(?>(?:...)*)`, is the same
language, is matched right by every 3.11, and stays linear for the same reason (the
engine never gives its text back).

A possessive repeat is matched right everywhere when no iteration can fail part of the
way: of one character (`[ \\t]*+`), or of a group that cannot fail once its first
character matched (`(?:[A-Z] *+[0-9]*+)++`: every item after that one may match
nothing). G-code's words are such a group, and the block checks run on every job line:
they keep their possessive repeats, which `re` runs faster than an atomic group.

Every pattern is found two ways: compiled at a module's top level or in a class (as
the module holds it), and as a literal handed to `re` anywhere in the source (read
with `ast`). docs/gcode.md, "Reading G-code in linear time".
"""

from __future__ import annotations

import ast
import importlib
import re
from collections.abc import Iterator
from pathlib import Path
from re import _constants as sre_constants  # type: ignore[attr-defined]
from re import _parser as sre_parser  # type: ignore[attr-defined]

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("hostd", "bench")
# One character wide, whatever it is: a repeat of it has no iteration to fail part-way.
_ONE_CHARACTER = {
    sre_constants.LITERAL,
    sre_constants.NOT_LITERAL,
    sre_constants.IN,
    sre_constants.ANY,
    sre_constants.CATEGORY,
}
_REPEATS = {sre_constants.MAX_REPEAT, sre_constants.MIN_REPEAT, sre_constants.POSSESSIVE_REPEAT}
_RE_CALLS = {
    "compile",
    "match",
    "fullmatch",
    "search",
    "sub",
    "subn",
    "split",
    "findall",
    "finditer",
}


def source_files() -> list[Path]:
    return sorted(path for package in PACKAGES for path in (ROOT / package).rglob("*.py"))


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def literal_patterns(path: Path) -> Iterator[tuple[str, str | bytes, int]]:
    """(where, pattern, flags) for each literal first argument of a call to `re`."""
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and isinstance(node.func.value, ast.Name)
            and node.func.value.id == "re"
            and node.func.attr in _RE_CALLS
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str | bytes)
        ):
            yield f"{path.relative_to(ROOT)}:{node.lineno}", node.args[0].value, 0


def compiled_patterns(name: str) -> Iterator[tuple[str, str | bytes, int]]:
    """(where, pattern, flags) for each pattern a module holds, or a class of it."""
    module = importlib.import_module(name)
    spaces = [(name, vars(module))]
    spaces += [
        (f"{name}.{key}", vars(value))
        for key, value in vars(module).items()
        if isinstance(value, type) and value.__module__ == name
    ]
    for where, space in spaces:
        for key, value in space.items():
            if isinstance(value, re.Pattern):
                yield f"{where}.{key}", value.pattern, value.flags


def fails_only_at_its_start(body: list[tuple[object, object]]) -> bool:
    """An iteration of `body` either fails on its first character or matches: that one is
    one character wide, and every item after it is a repeat that may match nothing."""
    first, *rest = body
    return first[0] in _ONE_CHARACTER and all(
        op in _REPEATS and value[0] == 0  # type: ignore[index]  # (min, max, body)
        for op, value in rest
    )


def possessive_groups(pattern: str | bytes, flags: int) -> list[str]:
    """Each possessive repeat in `pattern` that an iteration can fail part of the way in."""
    found: list[str] = []

    def walk(items: object) -> None:
        for op, value in items:  # type: ignore[attr-defined]
            if op is sre_constants.POSSESSIVE_REPEAT:
                low, high, body = value
                if not fails_only_at_its_start(list(body)):
                    found.append(f"{op} {low}..{high} of {list(body)!r:.60}")
            inside(value)

    def inside(value: object) -> None:
        """Every subpattern an item holds (a repeat's, a group's, each branch's)."""
        if isinstance(value, sre_parser.SubPattern):
            walk(value)
        elif isinstance(value, tuple | list):
            for part in value:
                inside(part)

    walk(sre_parser.parse(pattern, flags))
    return found


def every_pattern() -> list[tuple[str, str | bytes, int]]:
    found: list[tuple[str, str | bytes, int]] = []
    for path in source_files():
        found += literal_patterns(path)
        if not (name := module_name(path)).endswith("__main__"):
            found += compiled_patterns(name)
    return found


PATTERNS = every_pattern()


def test_the_scan_finds_the_patterns_it_must_judge() -> None:
    """The G-code tokenizer's, the block checks', and a literal in a function."""
    where = {place for place, _, _ in PATTERNS}
    for known in (
        "hostd.protocol.gcodewords._WORDS",
        "hostd.protocol.gcode._PLAIN_NUMBERED_SPACED",
        "hostd.protocol.grbl.codec._PLAIN_LINES",
        "hostd.protocol.textmode._COMMAND",
    ):
        assert known in where
    assert any(place.startswith("hostd/") and ":" in place for place in where)
    assert len(PATTERNS) > 50


@pytest.mark.parametrize(
    ("pattern", "flagged"),
    [
        (r"(?:ab?c)*+", True),  # cpython#106052's own example
        (r"(?:[ \t]*+X[0-9]++)++", True),
        (r"x(?:ab)?+", True),
        (r"(?>(?:ab?c)*)", False),
        (r"[ \t]*+[0-9]++x?+\)?+", False),
        (rb"(?:N[0-9]++\n)++", True),
        (r"(?:[A-Z] *+[0-9]{0,9}+(?:\.[0-9]*+)?+)++", False),  # G-code's words
        (r"(?:[A-Z] *+[0-9]++)++", True),  # `X` then no digit: fails part of the way
        (r"(?:(?!N)[A-Z]*+)++", True),  # a lookahead first is no character
    ],
)
def test_the_judge_tells_a_possessive_group_from_a_possessive_character(
    pattern: str | bytes, flagged: bool
) -> None:
    assert bool(possessive_groups(pattern, 0)) is flagged


def test_no_pattern_repeats_a_group_possessively() -> None:
    bad = {
        where: found
        for where, pattern, flags in PATTERNS
        if (found := possessive_groups(pattern, flags))
    }
    assert bad == {}, "use an atomic group, (?>(?:...)*), in place of (?:...)*+"
