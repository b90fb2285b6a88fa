"""Probing's words per dialect: how the probe input is seen, and the G10 that sets zero.

Plain calls on each session (hostd/protocol/probing.py, the sessions'
`probe_input` and `work_zero_line`); the whole probe over real ptys is in
tests/daemon/test_probing.py.
"""

from __future__ import annotations

import pytest

from hostd.protocol.commands import InvalidCommand
from hostd.protocol.g2core import G2Session
from hostd.protocol.grbl.session import GrblSession
from hostd.protocol.probing import ProbeInput, probe_line, touch_value


def g2(wcs: str | None = "G54") -> G2Session:
    session = G2Session("m1", clock=lambda: 0.0)
    session.model.modal["wcs"] = wcs
    return session


def test_g2core_reads_the_input_prbin_names_with_a_get() -> None:
    session = g2()
    assert session.probe_input_reads() == ['{"prbin": null}']
    assert session.probe_input([{"prbin": 5}]) == ProbeInput("in5", '{"in5": null}')


@pytest.mark.parametrize("answer", [{"prbin": 0}, {"prbin": None}, {"prbin": "x"}, {}])
def test_g2core_without_a_probe_input_refuses_to_probe(answer: dict[str, object]) -> None:
    with pytest.raises(InvalidCommand, match="no probe input configured"):
        g2().probe_input([answer])


def test_grbl_sees_the_probe_in_every_status_report() -> None:
    session = GrblSession("m1", clock=lambda: 0.0)
    assert session.probe_input_reads() == []
    assert session.probe_input([]) == ProbeInput("pin_p")


@pytest.mark.parametrize(("wcs", "p"), [("G54", 1), ("G55", 2), ("G59", 6)])
def test_g2core_zeroes_in_the_active_wcs_by_number(wcs: str, p: int) -> None:
    assert g2(wcs).work_zero_line({"z": 19.05}) == f"G10 L20 P{p} Z19.05"


@pytest.mark.parametrize("wcs", ["G53", None])
def test_g2core_refuses_to_zero_without_a_wcs_it_can_name(wcs: str | None) -> None:
    with pytest.raises(InvalidCommand, match="G54-G59"):
        g2(wcs).work_zero_line({"z": 1.0})


def test_grbl_zeroes_in_the_active_wcs_as_p0() -> None:
    session = GrblSession("m1", clock=lambda: 0.0)
    assert session.work_zero_line({"x": -13.175}) == "G10 L20 P0 X-13.175"


def test_the_probe_lines_and_what_the_touch_reads() -> None:
    assert probe_line("z", -25.0, 100.0) == "G38.2 Z-25 F100"
    assert probe_line("z", -7.5, 100.0, must_touch=False) == "G38.3 Z-7.5 F100"
    assert touch_value("z", 19.05, 6.35) == 19.05  # the tip on the plate's top
    assert touch_value("x", 10.0, 6.0) == -13.0  # the wall, then a radius, to the edge
