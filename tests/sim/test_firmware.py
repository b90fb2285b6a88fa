"""What real g2core boards print that a tidy simulator would not (issue 12, item 10).

Each test pins one behaviour to the firmware source it follows (synthetos/g2,
`g2core/`, edge-preview 1fb59404): the exact line the board prints, read off
the pty as a host reads it.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest

from hostd.protocol.states import MachineState
from hostd.protocol.status import message
from hostd.sim import SimController
from hostd.sim.callsites import CALL_SITES, CallSite
from hostd.sim.probing import TouchPlate

from .conftest import INSTANT, Host, Message, has_stat

pytestmark = pytest.mark.asyncio


def is_probe(m: Message) -> bool:
    return "prb" in m


async def answer(host: Host) -> bytes:
    """The next `{r}` line as printed (status reports before it skipped)."""
    while not (line := await host.line()).startswith(b'{"r"'):
        pass
    return line


# -- G38.x probing: cycle_probing.cpp -------------------------------------------


async def test_a_probe_that_touches_reports_where_it_touched(
    timed_sim: SimController, timed_host: Host
) -> None:
    timed_sim.probe_surface("z", -1.25)
    assert (await timed_host.ask(b"G38.2 Z-5 F600\n"))["f"] == [1, 0, 15]  # answered at once
    # _send_probe_report prints each axis with %0.5f, machine coordinates.
    raw = b""
    states: list[int] = []
    while not raw.startswith(b'{"prb"'):
        raw = await timed_host.line()
        states += [json.loads(raw)["sr"]["stat"]] if b'"stat"' in raw else []
    assert raw == (
        b'{"prb":{"e":1,"x":0.00000,"y":0.00000,"z":-1.25000,"a":0.00000,"b":0.00000,"c":0.00000}}'
    )
    assert MachineState.PROBE in states
    await timed_host.until(has_stat(MachineState.PROGRAM_STOP))
    assert timed_sim.position["z"] == pytest.approx(-1.25)
    # The motion mode is cancelled when the cycle ends (_probe_restore_settings).
    assert (await timed_host.ask(b"{momo:n}\n"))["r"] == {"momo": 4}


async def test_a_touch_plate_trips_the_probe_at_its_top_face(
    host: Host, sim: SimController
) -> None:
    sim.touch_plate(TouchPlate(top=-2.5))
    await host.ask(b"G38.2 Z-5 F600\n")
    (report,) = [m for m in await host.until(is_probe) if "prb" in m]
    assert report["prb"]["e"] == 1 and report["prb"]["z"] == -2.5
    # The bit rests on the plate: the probe input (in<prbin>) reads closed.
    assert (await host.ask(b"{prbin:n}\n"))["r"] == {"prbin": 5}
    assert (await host.ask(b"{in5:n}\n"))["r"] == {"in5": 1}


async def test_a_corner_plate_has_walls_the_bit_meets_by_its_radius(
    host: Host, sim: SimController
) -> None:
    sim.touch_plate(TouchPlate(top=-10.0, x_face=20.0, y_face=30.0, tool_radius=1.5))
    await host.ask(b"G0 Y35 Z-12\n")  # over the plate in Y, beside it in X, below its top
    await host.ask(b"G38.2 X40 F600\n")
    (report,) = [m for m in await host.until(is_probe) if "prb" in m]
    assert report["prb"]["e"] == 1 and report["prb"]["x"] == 18.5  # the face less the radius


async def test_the_operator_touching_the_plate_shows_on_the_probe_input(
    host: Host, sim: SimController
) -> None:
    assert (await host.ask(b"{in5:n}\n"))["r"] == {"in5": 0}
    sim.touch(reads=1)
    assert (await host.ask(b"{in5:n}\n"))["r"] == {"in5": 1}
    assert (await host.ask(b"{in5:n}\n"))["r"] == {"in5": 0}  # let go


async def test_with_no_probe_input_configured_a_probe_never_trips(
    host: Host, sim: SimController
) -> None:
    # prbin 0: gpio_read_input(0) reads false, so the plate is never felt (gpio.cpp).
    await host.ask(b"{prbin:0}\n")
    sim.touch_plate(TouchPlate(top=-2.5))
    await host.ask(b"G38.2 Z-5 F600\n")
    got = await host.until(is_probe)
    assert got[-1]["prb"]["e"] == 0 and got[-1]["prb"]["z"] == -5
    await sim.wait_state(MachineState.ALARM)


async def test_a_g38_2_that_never_touches_is_an_alarm_and_a_failed_report(
    host: Host, sim: SimController
) -> None:
    assert (await host.ask(b"G38.2 Z-5 F600\n"))["f"][1] == 0
    got = await host.until(is_probe)
    er = next(m["er"] for m in got if "er" in m)
    assert (er["st"], er["msg"]) == (250, "Probe cycle failed - probing failed")
    assert got[-1]["prb"]["e"] == 0 and got[-1]["prb"]["z"] == -5
    await sim.wait_state(MachineState.ALARM)


async def test_a_g38_3_that_never_touches_only_reports_it(host: Host, sim: SimController) -> None:
    await host.ask(b"G38.3 X10 F600\n")
    got = await host.until(is_probe)
    assert got[-1]["prb"]["e"] == 0 and got[-1]["prb"]["x"] == 10
    assert not [m for m in got if "er" in m]
    await host.until(has_stat(MachineState.PROGRAM_STOP))


async def test_a_g38_4_trips_as_the_tool_leaves_the_surface(host: Host, sim: SimController) -> None:
    sim.probe_surface("z", 0.0)  # touching where it stands
    await host.ask(b"G38.4 Z5 F600\n")
    assert (await host.until(is_probe))[-1]["prb"]["e"] == 1


@pytest.mark.parametrize(
    ("line", "status", "detail"),
    [
        (b"G38.2 Z-5\n", 142, "Feedrate is zero"),  # cm_straight_probe, before anything runs
        (b"G38.2 F100\n", 134, "Axis is missing"),
    ],
)
async def test_a_probe_refused_when_read_is_an_alarm_and_its_answer(
    host: Host, sim: SimController, line: bytes, status: int, detail: str
) -> None:
    host.send(line)
    got = await host.until(lambda m: "r" in m)
    assert got[0]["er"]["st"] == status and got[0]["er"]["msg"].endswith(f" - {detail}")
    assert got[-1]["f"][1] == status  # cm_alarm's status is the line's answer too
    await sim.wait_state(MachineState.ALARM)


@pytest.mark.parametrize(
    ("surface", "line", "status"),
    [
        (("z", 0.0), b"G38.2 Z-5 F600\n", 254),  # the probe already touches
        (None, b"G38.2 Z-0.1 F600\n", 251),  # less than MINIMUM_PROBE_TRAVEL
    ],
)
async def test_a_probe_that_cannot_start_is_a_probe_error(
    host: Host, sim: SimController, surface: tuple[str, float] | None, line: bytes, status: int
) -> None:
    if surface is not None:
        sim.probe_surface(*surface)
    await host.ask(line)
    got = await host.until(has_stat(MachineState.ALARM))
    er = next(m["er"] for m in got if "er" in m)
    assert er["st"] == status and er["msg"].endswith(" - probe error")
    assert not [m for m in got if "prb" in m]  # _probing_exception_exit sends no report


async def test_no_line_is_read_until_the_probe_cycle_ends(
    timed_sim: SimController, timed_host: Host
) -> None:
    timed_sim.probe_surface("z", -2.0)
    timed_host.send(b"G38.2 Z-5 F600\nG0 X1\n")
    got = await timed_host.until(lambda m: "r" in m and m["f"][2] == 6)
    assert any("prb" in m for m in got)  # G0 X1 was answered only after the report


# -- a failed homing: cycle_homing.cpp _homing_error_exit ---------------------


async def test_a_failed_homing_prints_an_extra_answer_and_no_alarm(
    host: Host, sim: SimController
) -> None:
    sim.fail_homing("y", 246)
    assert (await host.ask(b"G28.2 X0 Y0\n"))["f"] == [1, 0, 12]
    extra = await host.response()
    assert extra == {
        "r": {"msg": f"Y axis {message(246)}"},
        "f": [1, 240, 1],  # cs.linelen was reset by the line's own answer
    }
    await host.until(has_stat(MachineState.PROGRAM_STOP))
    assert not sim.homed
    assert (await host.ask(b"G0 X1\n"))["f"][1] == 0  # no alarm: the next lines run
    sim.fail_homing(None)
    await host.ask(b"G28.2 X0 Y0 Z0\n")
    await sim.wait_for(lambda: sim.homed)


# -- status 15: report.cpp _startup_helper, config.cpp set_defaults ------------


async def test_defa_prints_its_initializing_message_with_the_lines_count(
    host: Host, sim: SimController
) -> None:
    assert (await host.ask(b"{si:500}\n"))["r"] == {"si": 500}
    host.send(b"{defa:1}\n")
    init = await host.response()
    assert init["r"]["msg"] == "Initializing configs to default settings"
    assert init["f"] == [1, 15, 10]  # it took the line's count...
    assert await host.response() == {"r": {"defa": True}, "f": [1, 0, 1]}  # ...and left 1
    assert (await host.ask(b"{si:n}\n"))["r"] == {"si": 20}  # the profile's default again


async def test_a_uart_board_prints_its_boot_messages_after_a_reset(tmp_path: Path) -> None:
    config = dataclasses.replace(INSTANT, uart=True)
    async with SimController(str(tmp_path / "ttyS"), config=config) as sim:
        await sim.reset()
        host = await Host.open(sim.data_path, banner=False)
        try:
            loading = await host.message()
            assert loading["r"]["msg"] == "Loading configs from EEPROM"
            assert loading["f"] == [1, 15, 1]
            assert (await host.message())["r"]["msg"] == "SYSTEM READY"
        finally:
            await host.close()


# -- bare nan and inf: util.cpp floattoa ----------------------------------------


async def test_a_value_the_firmware_computed_wrong_is_printed_bare(
    host: Host, sim: SimController
) -> None:
    sim.glitch("vel", math.nan)
    host.send(b"{sr:n}\n")
    assert b'"vel":nan' in await answer(host)
    sim.glitch("vel", -math.inf)
    host.send(b"{vel:n}\n")
    assert await answer(host) == b'{"r":{"vel":-inf},"f":[1,0,9]}'
    sim.glitch("vel", None)
    assert (await host.ask(b"{vel:n}\n"))["r"] == {"vel": 0}


# -- answers that do not fit: json_parser.cpp json_print_response --------------


async def test_an_answer_too_long_is_an_exception_report_or_nothing(
    host: Host, sim: SimController
) -> None:
    sim.set_output_buffer(100)
    host.send(b"{sys:n}\n")
    assert await host.message() == {
        "er": {
            "fb": 101.06,
            "st": 113,
            "msg": "JSON string too long - json_print_response() json too long",
        }
    }
    assert (await host.ask(b"{si:n}\n"))["f"] == [1, 0, 8]  # short answers still fit
    sim.set_output_buffer(100, reported=False)
    host.send(b"{sys:n}\n{xvm:n}\n")
    assert await host.message() == {"r": {"xvm": 6000}, "f": [1, 0, 9]}  # sys's never came


# -- exceptions from their call sites: alarm.cpp ---------------------------------


def _id(site: CallSite) -> str:
    return f"{site.status}-{site.where}"


@pytest.mark.parametrize("site", CALL_SITES, ids=_id)
async def test_every_firmware_call_site_raises_its_report_and_lockout(
    host: Host, sim: SimController, site: CallSite
) -> None:
    sim.firmware_exception(site)
    want = {"alarm": 2, "shutdown": 12, "panic": 13}[site.path]
    er = (await host.message())["er"]
    assert er["st"] == site.status and er["msg"].endswith(f" - {site.detail}")
    await sim.wait_state(MachineState(want))
    if site.path == "panic":
        # cm_panic() requests no status report: the next line out is our own answer.
        assert (await host.ask(b"{stat:n}\n"))["r"] == {"stat": 13}
    else:
        assert (await host.until(has_stat(want)))[-1]["sr"]["stat"] == want


# -- TinyG's answers: [TG] json_parser.c ---------------------------------------


async def test_a_tinyg_answers_with_a_checksum_footer(tmp_path: Path) -> None:
    config = dataclasses.replace(INSTANT, fb=440.21)
    async with SimController(str(tmp_path / "tty"), config=config) as sim:
        host = await Host.open(sim.data_path, banner=False)
        try:
            await host.message()  # its banner
            answer = await host.ask(b"{fb:n}\n")
            assert answer["r"] == {"fb": 440.21} and len(answer["f"]) == 4
        finally:
            await host.close()


# -- the tool-length sensor and the tool table (issue 29) ----------------------------


async def test_a_probe_over_the_tool_sensor_trips_higher_for_a_longer_tool(
    timed_sim: SimController, timed_host: Host
) -> None:
    timed_sim.tool_sensor(-5.0, -5.0, -3.0)
    timed_sim.probe_surface("z", -4.5)  # the table, elsewhere
    await timed_host.ask(b"G53 G0 X-5 Y-5\n")
    await timed_host.until(has_stat(MachineState.PROGRAM_STOP))
    timed_sim.tool_length(1.5)
    await timed_host.ask(b"G38.2 Z-5 F600\n")
    report = await _probe_report(timed_host)
    assert report["e"] == 1 and report["z"] == pytest.approx(-1.5)
    # Away from the sensor the test's surface is what the probe finds.
    await timed_host.until(has_stat(MachineState.PROGRAM_STOP))
    await timed_host.ask(b"G53 G0 X0 Y0\n")
    await timed_host.until(has_stat(MachineState.PROGRAM_STOP))
    await timed_host.ask(b"G38.2 Z-5 F600\n")
    assert (await _probe_report(timed_host))["z"] == pytest.approx(-4.5)


async def _probe_report(host: Host) -> dict[str, float]:
    raw = b""
    while not raw.startswith(b'{"prb"'):
        raw = await host.line()
    report: dict[str, float] = json.loads(raw)["prb"]
    return report


async def test_a_tool_table_offset_moves_every_target_until_g49(
    timed_sim: SimController, timed_host: Host
) -> None:
    """G10 L1 writes the entry, G43 H applies it (cm_set_tl_offset), G49 cancels it;
    an H past the table is 171 and a P past it 161 (canonical_machine.cpp)."""
    assert (await timed_host.ask(b"G10 L1 P2 Z3.5\n"))["f"][1] == 0
    assert (await timed_host.ask(b"G43 H2\n"))["f"][1] == 0
    await timed_host.ask(b"G0 Z-1\n")
    await timed_host.until(has_stat(MachineState.PROGRAM_STOP))
    assert timed_sim.position["z"] == pytest.approx(2.5)
    await timed_host.ask(b"G49\n")
    await timed_host.ask(b"G0 Z-1\n")
    await timed_host.until(has_stat(MachineState.PROGRAM_STOP))
    assert timed_sim.position["z"] == pytest.approx(-1.0)
    assert (await timed_host.ask(b"G43 H33\n"))["f"][1] == 171
    assert (await timed_host.ask(b"G10 L1 P33 Z1\n"))["f"][1] == 161
