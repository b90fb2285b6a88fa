"""Which lines are maintenance commands, by plain calls (protocol/maintenance.py)."""

from __future__ import annotations

import pytest

from hostd.protocol.maintenance import (
    SANE_JOG_MM,
    Kind,
    g2core_powered,
    grbl_powered,
    maintenance_command,
    startup_block_acts,
    startup_blocks,
)

TRAVEL = {"x": (-300.0, 0.0), "y": (-200.0, 0.0), "z": (-80.0, 0.0)}


@pytest.mark.parametrize(
    ("line", "kind"),
    [
        ("$RST=$", Kind.RESTORE),
        ("$RST=#", Kind.RESTORE),
        ("$RST=*", Kind.RESTORE),
        ("$rst=&", Kind.RESTORE),  # grblHAL; grbl upper-cases what it reads
        ("$ R S T = *", Kind.RESTORE),  # and drops the blanks
        ("$N0=G0X10", Kind.STARTUP_BLOCK),
        ("$n1 = g54 (set the origin)", Kind.STARTUP_BLOCK),
        ("$N1=", Kind.STARTUP_BLOCK),  # erasing one is storing too
        ("$I=my laser", Kind.BUILD_INFO),
        ("$SLP", Kind.SLEEP),
        ("$J=G91 X9999999999 F100", Kind.ABSURD_JOG),
        ("$J=G91 Y-201 F100", Kind.ABSURD_JOG),  # more than Y travels
        ("$J=G53 X5 F100", Kind.ABSURD_JOG),  # a machine target outside the travel
        ("$J=G91 G20 X12 F10", Kind.ABSURD_JOG),  # 304.8 mm
        ("$J=G91 X1.2.3 F10", Kind.ABSURD_JOG),  # unreadable
    ],
)
def test_grbl_maintenance_commands(line: str, kind: Kind) -> None:
    found = maintenance_command("grbl", line, travel=TRAVEL)
    assert found is not None and found.kind is kind


@pytest.mark.parametrize(
    "line",
    [
        "$N",
        "$I",
        "$$",
        "$#",
        "$G",
        "$X",
        "$H",
        "$110=500",
        "G0 X10",
        "$J=G91 X-10 F600",
        "$J=G53 X-150 Y-100 F600",
        "G0 X1 (flash)",
    ],
)
def test_ordinary_grbl_lines_are_not_maintenance(line: str) -> None:
    assert maintenance_command("grbl", line, travel=TRAVEL) is None


def test_without_travel_a_jog_is_bounded_by_the_documented_sane_bound() -> None:
    assert maintenance_command("grbl", f"$J=G91 X{SANE_JOG_MM - 1:g} F100") is None
    found = maintenance_command("grbl", f"$J=G91 X{SANE_JOG_MM + 1:g} F100")
    assert found is not None and found.kind is Kind.ABSURD_JOG and not found.on_purpose
    # In a G20 board a jog without units is read in inches.
    assert maintenance_command("grbl", "$J=G91 X500 F10", inches=True) is not None
    assert maintenance_command("grbl", "$J=G91 G21 X500 F10", inches=True) is None


@pytest.mark.parametrize(
    ("line", "kind"),
    [
        ("{defa:1}", Kind.RESTORE),
        ("$defa=1", Kind.RESTORE),
        ('{"flash":true}', Kind.BOOTLOADER),
        ("{boot:1}", Kind.BOOTLOADER),
    ],
)
def test_g2core_defaults_and_bootloader_are_never_on_purpose(line: str, kind: Kind) -> None:
    found = maintenance_command("g2core", line)
    assert found is not None and found.kind is kind and not found.on_purpose


@pytest.mark.parametrize(
    ("block", "acts"),
    [
        ("G54G21", None),
        ("G20G17G90", None),
        ("G92X0Y0", None),
        ("G10L2P1X-5", None),
        ("G0X-100", "moves the machine (G0)"),
        ("G1Z-5F100", "moves the machine (G1)"),
        ("G28", "moves the machine (G28)"),
        ("X-10", "moves the machine (X-10 in the motion mode in force, G0 at reset)"),
        ("M3S1000", "starts the spindle or laser (M3)"),
        ("M8", "starts the coolant (M8)"),
    ],
)
def test_what_a_startup_block_does_at_a_reset(block: str, acts: str | None) -> None:
    assert startup_block_acts(block) == acts


def test_startup_blocks_are_read_from_the_n_settings_in_order() -> None:
    blocks = startup_blocks({"N1": "G0X-5", "32": "1", "N0": "", "130": "300"})
    assert [(b.n, b.line, b.acts) for b in blocks] == [(1, "G0X-5", "moves the machine (G0)")]


def test_a_long_adversarial_line_is_read_in_linear_time() -> None:
    # Word patterns whose classes do not overlap: no backtracking, whatever the input.
    line = "$J=" + "X" * 50_000 + "1" * 50_000 + "(" * 10_000
    assert maintenance_command("grbl", line, travel=TRAVEL) is not None


# -- what a fault that blocks a job forbids a sent line (machine.send, .maintenance) --


@pytest.mark.parametrize(
    ("line", "does"),
    [
        ("G1 X10 F100", "moves the machine (G1)"),
        ("x10", "moves the machine (X10 in the motion mode in force)"),
        ("G53 G0 Z-1", "moves the machine (G0)"),
        ("G38.2 Z-10 F50", "moves the machine (G38.2)"),
        ("M3 S1000", "starts the spindle or laser (M3)"),
        ("m4", "starts the spindle or laser (M4)"),
        ("$J=G91 X1 F100", "jogs the machine ($J=)"),
        ("$H", "homes the machine ($H)"),
        ("$HX", "homes the machine ($H)"),
        ("$N0=G0 X5", "moves the machine (G0)"),  # run once as it is stored
        ("$N0=G54", None),
        ("M5", None),  # stopping only makes safe
        ("M8", None),  # coolant on makes nothing less safe
        ("G10 L20 P1 X0", None),  # setting zero moves nothing
        ("G92 X0", None),
        ("G90 G21", None),
        ("(G1 X10)", None),  # a comment
        ("$G", None),
        ("$X", None),
        ("$$", None),
        ("?", None),
    ],
)
def test_what_a_line_sent_to_grbl_does_that_a_fault_forbids(line: str, does: str | None) -> None:
    assert grbl_powered(line) == does


@pytest.mark.parametrize(
    ("line", "does"),
    [
        ("G0 X10", "moves the machine (G0)"),
        ('{"gc":"G1 X1 F100"}', "moves the machine (G1)"),
        ('{gc:"m3 s500"}', "starts the spindle or laser (M3)"),
        ('{"GC":"G28.2 X0"}', "moves the machine (G28.2)"),  # a homing cycle
        ('{"gc":"G28.3 X0"}', None),  # sets the position: nothing moves
        ("{sr:n}", None),
        ('{"xvm":6000}', None),
        ('{"gc":"M5"}', None),
        ('{"gc":"G10 L20 P1 X0"}', None),
        ("$xvm=6000", None),
        ("{gc:", None),  # misread JSON: refused on its own (validate_line)
        ("M5", None),
    ],
)
def test_what_a_line_sent_to_g2core_does_that_a_fault_forbids(line: str, does: str | None) -> None:
    assert g2core_powered(line) == does


def test_a_long_adversarial_sent_line_is_judged_in_linear_time() -> None:
    line = "G1" + "X" * 50_000 + "1" * 50_000 + "(" * 10_000
    assert grbl_powered(line) is not None
    assert g2core_powered('{"gc":"' + line + '"}') is not None
