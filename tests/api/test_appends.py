"""What one connection remembers of its uploads (appends.py): bounded, most recent kept."""

from __future__ import annotations

from hostd.api.appends import MAX_NAMES, Chain


def test_a_connection_remembers_its_most_recent_names_only() -> None:
    chain = Chain()
    for i in range(MAX_NAMES + 10):
        chain.published(f"f{i}.gcode", (1, i, i, 7))
    chain.published("f20.gcode", (1, 99, 99, 7))  # uploaded again: most recent now

    assert len(chain.versions) == MAX_NAMES
    assert chain.last("f0.gcode") is None and chain.last("f9.gcode") is None
    assert chain.last("f20.gcode") == (1, 99, 99, 7)
    assert chain.last(f"f{MAX_NAMES + 9}.gcode") == (1, MAX_NAMES + 9, MAX_NAMES + 9, 7)
    chain.published("new.gcode", (1, 1000, 1, 7))
    assert chain.last("f10.gcode") is None and chain.last("f20.gcode") is not None
