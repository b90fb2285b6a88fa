"""The simulated grbl 1.1h / grblHAL over a real pty, spoken to in raw bytes."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import pytest

from hostd.sim.grbl import GrblConfig, GrblSimController
from hostd.sim.probing import TouchPlate

from .conftest import CLASSIC, HAL, GrblHost, connect, is_answer

pytestmark = pytest.mark.asyncio

# Moves take real time: 1 mm at F600 is 0.1 s (speed_factor 1).
TIMED_HAL = replace(HAL, instant=False, feedhold_decel=0.02, homing_time=0.1)
TIMED_CLASSIC = replace(CLASSIC, instant=False, feedhold_decel=0.02)


class Board:
    """A simulator plus a connected host, for tests that need their own config."""

    def __init__(self, tmp_path: Path, config: GrblConfig) -> None:
        self.sim = GrblSimController(str(tmp_path / "ttyG"), config)
        self.host: GrblHost | None = None

    async def __aenter__(self) -> tuple[GrblSimController, GrblHost]:
        await self.sim.start()
        self.host = await connect(self.sim)
        return self.sim, self.host

    async def __aexit__(self, *exc: object) -> None:
        if self.host is not None:
            self.host.close()
        await self.sim.stop()


# --- banner, CRLF, $I


async def test_classic_banner_is_crlf_framed(classic_host: GrblHost) -> None:
    assert bytes(classic_host.raw).endswith(b"\r\nGrbl 1.1h ['$' for help]\r\n")


async def test_grblhal_banner_is_crlf_framed(hal_host: GrblHost) -> None:
    assert bytes(hal_host.raw).endswith(b"\r\nGrblHAL 1.1f ['$' or '$HELP' for help]\r\n")


async def test_opening_an_arduino_grbl_resets_it(tmp_path: Path) -> None:
    config = replace(CLASSIC, reset_on_open=None)  # classic default: DTR resets the board
    async with GrblSimController(str(tmp_path / "ttyA"), config) as sim:
        host = GrblHost(sim.path)
        try:
            assert await host.line() == ""
            assert await host.line() == "Grbl 1.1h ['$' for help]"
        finally:
            host.close()


async def test_build_info_gives_planner_blocks_and_rx_buffer(
    classic_host: GrblHost, hal_host: GrblHost
) -> None:
    got = await classic_host.ask(b"$I\n")
    assert got == ["[VER:1.1h.20190830:]", "[OPT:V,15,128]", "ok"]
    got = await hal_host.ask(b"$I\n")
    assert got[0] == "[VER:1.1f.20260817:]"
    assert got[1] == "[OPT:VNML+,100,1024,3,0]"
    assert "[FIRMWARE:grblHAL]" in got and got[-1] == "ok"


@pytest.mark.parametrize(
    ("config", "opt", "reports"),
    [
        (TIMED_CLASSIC, "V,15,128", False),  # gnea/grbl config.h: USE_LINE_NUMBERS off
        (replace(TIMED_CLASSIC, line_numbers=True), "VN,15,128", True),
        (TIMED_HAL, "VNML+,100,1024,3,0", True),  # grblHAL: always
    ],
)
async def test_a_running_lines_number_is_reported_only_by_a_build_that_keeps_it(
    tmp_path: Path, config: GrblConfig, opt: str, reports: bool
) -> None:
    """`[OPT:]` has `N` exactly when a report has `Ln:` (gnea/grbl report.c:379-381 and
    :540-548 under one `#ifdef`); a default classic board parses the N and keeps none."""
    async with Board(tmp_path, config) as (sim, host):
        assert (await host.ask(b"$I\n"))[1] == f"[OPT:{opt}]"
        assert await host.ask(b"N7 G1 X-3 F600\n") == ["ok"]
        await sim.wait_state("Run")
        assert ("|Ln:7|" in await host.status()) is reports
        host.send(b"!")
        await sim.wait_state("Hold:0")


async def test_every_output_line_ends_crlf(hal_host: GrblHost) -> None:
    await hal_host.ask(b"$$\n")
    await hal_host.ask(b"$#\n")
    text = bytes(hal_host.raw)
    assert text.count(b"\n") == text.count(b"\r\n") > 40


# --- streaming and the receive buffer


async def test_a_character_counted_stream_is_all_ok(classic: GrblSimController) -> None:
    host = await connect(classic)
    lines = [f"G1 X-{i % 50}.5 Y-{i % 7} F3000\n".encode() for i in range(1000)]
    budget, in_flight, answers, sent = 128, [], [], 0
    while len(answers) < len(lines):
        while sent < len(lines) and sum(in_flight) + len(lines[sent]) <= budget:
            host.send(lines[sent])
            in_flight.append(len(lines[sent]))
            sent += 1
        answers.append(await host.until(is_answer))
        in_flight.pop(0)
    assert all(a[-1] == "ok" for a in answers)
    assert classic.board.rx_dropped == 0
    await classic.wait_state("Idle")
    host.close()


async def test_a_dwell_runs_in_the_boards_time_as_a_move_does(tmp_path: Path) -> None:
    """`speed_factor` divides a G4 as it divides a move (and as the g2core simulator
    does): 5 s of the machine's on a board ten times as fast end 0.5 s on."""
    async with Board(tmp_path, replace(TIMED_CLASSIC, speed_factor=10.0)) as (sim, host):
        host.send(b"G4 P5\n")
        await sim.wait_for(lambda: sim.board._wait is not None and sim.board._wait.kind == "dwell")
        wait = sim.board._wait
        assert wait is not None and wait.until - time.monotonic() <= 0.5
        assert await host.until(is_answer) == ["ok"]


async def test_overfilling_the_receive_buffer_loses_characters(tmp_path: Path) -> None:
    async with Board(tmp_path, TIMED_CLASSIC) as (sim, host):
        host.send(b"G4 P0.3\n")  # the main loop is busy for 0.3 s: nothing is read
        await sim.wait_for(lambda: sim.board._wait is not None and not sim.board.rx)
        burst = b"G0 X-1\n" * 28 + b"G0 X"  # 200 bytes into a 128-byte ring
        host.send(burst)
        await sim.wait_for(lambda: sim.board.rx_dropped == 200 - 128)
        answers = [(await host.until(is_answer))[-1] for _ in range(1 + 18)]
        assert answers == ["ok"] * 19  # the dwell, then the 18 whole lines the ring kept
        assert bytes(sim.board._line) == b"G0"  # what is left of the 19th line
        host.send(b"\n")
        assert await host.until(is_answer) == ["ok"]  # "G0": the rest of it was lost
        assert (await host.status()).startswith("<Idle|")
        assert sim.board.rx_dropped == 72


async def test_a_full_planner_holds_the_next_line_until_a_block_finishes(tmp_path: Path) -> None:
    config = replace(TIMED_CLASSIC, planner_blocks=2)
    async with Board(tmp_path, config) as (sim, host):
        for x in (1, 2, 3):
            host.send(f"G1 X-{x} F600\n".encode())
        assert await host.line() == "ok"
        assert await host.line() == "ok"
        assert sim.board._wait is not None  # the third waits for room
        assert await host.line() == "ok"
        assert len(sim.board.planner) <= 2


# --- errors


async def test_grblhal_error_latch_until_an_empty_line(hal_host: GrblHost) -> None:
    assert await hal_host.ask(b"G1 X-1\n") == ["error:22"]  # no feed rate yet
    assert await hal_host.ask(b"G0 X-1\n") == ["error:22"]  # latched: not run
    assert await hal_host.ask(b"\n") == ["ok"]
    assert await hal_host.ask(b"G0 X-1\n") == ["ok"]


async def test_grblhal_error_latch_cleared_by_a_dollar_command(hal_host: GrblHost) -> None:
    assert await hal_host.ask(b"G1 X-1\n") == ["error:22"]
    assert (await hal_host.ask(b"$G\n"))[-1] == "ok"
    assert await hal_host.ask(b"G0 X-1\n") == ["ok"]


async def test_grblhal_crlf_after_an_error_is_an_empty_line(hal_host: GrblHost) -> None:
    hal_host.send(b"G1 X-1\r\nG0 X-1\r\n")
    got = [(await hal_host.until(is_answer))[-1] for _ in range(3)]
    assert got == ["error:22", "ok", "ok"]  # the LF after the error clears the latch


async def test_classic_grbl_has_no_latch(classic_host: GrblHost) -> None:
    assert await classic_host.ask(b"G1 X-1\n") == ["error:22"]
    assert await classic_host.ask(b"G0 X-1\n") == ["ok"]


# --- alarms


async def test_limit_switch_in_motion_on_grblhal(tmp_path: Path) -> None:
    config = replace(TIMED_HAL, hard_limits=True)
    async with Board(tmp_path, config) as (sim, host):
        assert await host.ask(b"G1 X-20 F600\n") == ["ok"]
        await sim.wait_state("Run")
        sim.limit_switch("x")
        assert await host.until(lambda s: s.startswith("[MSG")) == [
            "ALARM:1",
            "[MSG:Reset to continue]",
        ]
        assert await host.ask(b"$X\n") == ["error:79"]
        assert await host.ask(b"G0 X0\n") == ["error:9"]
        assert (await host.ask(b"$G\n"))[-1] == "ok"  # allowed while blocked
        assert "Pn:X" in await host.status()
        sim.limit_switch("x", active=False)
        host.send(b"\x18")
        got = await host.until(lambda s: s.startswith("[MSG"))
        assert got[-2:] == ["GrblHAL 1.1f ['$' or '$HELP' for help]", "[MSG:'$H'|'$X' to unlock]"]
        assert await host.ask(b"G0 X0\n") == ["error:9"]
        assert await host.ask(b"$X\n") == ["[MSG:Caution: Unlocked]", "ok"]
        assert await host.ask(b"G0 X-1\n") == ["ok"]


async def test_limit_switch_on_classic_grbl_reads_no_lines_until_reset(tmp_path: Path) -> None:
    config = replace(TIMED_CLASSIC, hard_limits=True)
    async with Board(tmp_path, config) as (sim, host):
        assert await host.ask(b"G1 X-20 F600\n") == ["ok"]
        await sim.wait_state("Run")
        sim.limit_switch("x")
        assert await host.until(lambda s: s.startswith("[MSG")) == [
            "ALARM:1",
            "[MSG:Reset to continue]",
        ]
        host.send(b"$X\n")
        assert (await host.status()).startswith("<Alarm|")  # `?` works, the line waits
        assert sim.board.rx  # unread
        sim.limit_switch("x", active=False)
        host.send(b"\x18")
        got = await host.until(lambda s: s.startswith("[MSG"))
        assert got[-1] == "[MSG:'$H'|'$X' to unlock]"
        assert await host.ask(b"$X\n") == ["[MSG:Caution: Unlocked]", "ok"]


async def test_soft_limit_alarm_refuses_unlock_with_79(tmp_path: Path) -> None:
    config = replace(HAL, homing=True, soft_limits=True)
    async with Board(tmp_path, config) as (_sim, host):
        assert (await host.ask(b"$H\n"))[-1] == "ok"
        host.send(b"G0 X5\n")  # outside [-200, 0]
        assert await host.until(lambda s: s.startswith("[MSG")) == [
            "ALARM:2",
            "[MSG:Reset to continue]",
        ]
        assert await host.ask(b"$X\n") == ["error:79"]
        host.send(b"\x18")
        await host.until(lambda s: s == "[MSG:'$H'|'$X' to unlock]")
        assert await host.ask(b"$X\n") == ["[MSG:Caution: Unlocked]", "ok"]


async def test_grblhal_homing_required_is_alarm_11(tmp_path: Path) -> None:
    config = replace(HAL, homing=True, homing_init_lock=True)
    async with Board(tmp_path, config) as (sim, host):
        # ALARM:11 went out at power-on, to nobody; after the 0x18 the alarm is still 11,
        # so system_raise_alarm does not print it again: only the message comes.
        assert await host.line() == "[MSG:Homing cycle required]"
        assert sim.board.alarm == 11
        assert await host.ask(b"$X\n") == ["error:46"]
        assert await host.ask(b"G0 X-1\n") == ["error:9"]
        assert (await host.ask(b"$H\n"))[-2:] == ["[MSG:]", "ok"]
        assert (await host.status()).startswith("<Idle|MPos:-1.000,-1.000,-1.000")


async def test_grblhal_estop(hal: GrblSimController) -> None:
    host = await connect(hal)
    hal.estop(True)
    assert await host.until(lambda s: s.startswith("[MSG")) == [
        "ALARM:10",
        "[MSG:Emergency stop - clear, then reset to continue]",
    ]
    host.send(b"\x18")  # refused while the input is held
    status = await host.status()
    assert status.startswith("<Alarm|") and "Pn:E" in status
    hal.estop(False)
    host.send(b"\x18")
    got = await host.until(lambda s: s.startswith("[MSG"))
    assert got[-1] == "[MSG:'$H'|'$X' to unlock]"
    assert await host.ask(b"$X\n") == ["[MSG:Caution: Unlocked]", "ok"]
    host.close()


async def test_reset_in_motion_loses_position_alarm_3(tmp_path: Path) -> None:
    async with Board(tmp_path, TIMED_HAL) as (sim, host):
        assert await host.ask(b"G1 X-20 F600\n") == ["ok"]
        await sim.wait_state("Run")
        host.send(b"\x18")
        got = await host.until(lambda s: s.startswith("[MSG"))
        assert got == [
            "ALARM:3",
            "",
            "GrblHAL 1.1f ['$' or '$HELP' for help]",
            "[MSG:'$H'|'$X' to unlock]",
        ]
        assert (await host.status()).startswith("<Alarm|")


async def test_reset_while_idle_keeps_idle(classic_host: GrblHost) -> None:
    classic_host.send(b"\x18")
    await classic_host.until(lambda s: s.startswith("Grbl "))
    assert (await classic_host.status()).startswith("<Idle|")


# --- hold, door, jog, probe, check mode


async def test_hold_and_resume(tmp_path: Path) -> None:
    async with Board(tmp_path, TIMED_HAL) as (sim, host):
        assert await host.ask(b"G1 X-3 F600\n") == ["ok"]
        await sim.wait_state("Run")
        host.send(b"!")
        await sim.wait_state("Hold:0")
        x = sim.position["x"]
        assert -3 < x < 0
        assert (await host.status()).startswith("<Hold:0|")
        host.send(b"~")
        await sim.wait_state("Idle")
        assert sim.position["x"] == -3


@pytest.mark.parametrize("flavour", ["grbl", "grblhal"])
async def test_build_info_and_startup_lines_are_refused_while_moving(
    tmp_path: Path, flavour: str
) -> None:
    """`$I` and `$N` only in Idle and Alarm: gnea/grbl system.c:172-175 (`$I` :205, `$N`
    :237); grblHAL core system.c:635 and :726. `$G` any time."""
    timed = GrblConfig(flavour=flavour, speed_factor=1.0, feedhold_decel=0.02)
    async with Board(tmp_path, timed) as (sim, host):
        host.send(b"G1 X-3 F600\n")  # classic grbl: after its reset's second banner
        await host.until(lambda s: s == "ok")
        await sim.wait_state("Run")
        assert await host.ask(b"$I\n") == ["error:8"]
        assert await host.ask(b"$N\n") == ["error:8"]
        assert (await host.ask(b"$G\n"))[-1] == "ok"
        host.send(b"!")
        await sim.wait_state("Hold:0")
        host.send(b"$I\n")  # held: read by no main-loop pass, and a reset empties it
        host.send(b"\x18")
        await host.until(lambda s: s.startswith(("Grbl ", "GrblHAL ")))
        assert (await host.ask(b"$I\n"))[-1] == "ok"


async def test_door_stops_then_resumes_when_closed(tmp_path: Path) -> None:
    async with Board(tmp_path, TIMED_HAL) as (sim, host):
        assert await host.ask(b"G1 X-3 F600\n") == ["ok"]
        await sim.wait_state("Run")
        sim.door(True)
        assert await host.line() == "[MSG:Check Door]"
        await sim.wait_state("Door:1")
        assert "Pn:D" in await host.status()
        host.send(b"~")  # refused while ajar
        assert (await host.status()).startswith("<Door:1|")
        sim.door(False)
        await sim.wait_state("Door:0")
        host.send(b"~")
        await sim.wait_state("Idle")
        assert sim.position["x"] == -3


async def test_jog_and_jog_cancel(tmp_path: Path) -> None:
    async with Board(tmp_path, TIMED_HAL) as (sim, host):
        assert await host.ask(b"G1 X-1\n") == ["error:22"]
        assert await host.ask(b"$J=G91 X-10\n") == ["error:22"]  # a jog needs F
        assert await host.ask(b"$J=G91 X-10 F600\n") == ["ok"]
        await sim.wait_state("Jog")
        assert await host.ask(b"G0 X0\n") == ["error:9"]
        host.send(b"\x85")
        await sim.wait_state("Idle")
        assert -10 < sim.position["x"] < 0
        assert (await host.ask(b"$G\n"))[0].startswith("[GC:G0 G54 G17 G21 G90")  # modes kept


async def test_probe_cycle_reports_prb(tmp_path: Path) -> None:
    async with Board(tmp_path, TIMED_HAL) as (sim, host):
        host.send(b"G38.2 Z-10 F600\n")
        await sim.wait_state("Run")
        sim.probe(True)
        got = await host.until(is_answer)
        assert got[-1] == "ok"
        z = sim.position["z"]
        assert got[0] == f"[PRB:0.000,0.000,{z:.3f}:1]" and -10 < z < 0
        assert (await host.ask(b"$#\n"))[-2] == f"[PRB:0.000,0.000,{z:.3f}:1]"


async def test_probe_over_the_tool_sensor_closes_on_it(tmp_path: Path) -> None:
    """The sensor closes the probe input where a tool of this length reaches it."""
    async with Board(tmp_path, TIMED_HAL) as (sim, host):
        sim.tool_sensor(-5.0, -5.0, -3.0)
        sim.tool_length(1.5)
        assert await host.ask(b"G53 G0 X-5 Y-5\n") == ["ok"]
        assert await host.ask(b"G38.2 Z-10 F600\n") == ["[PRB:-5.000,-5.000,-1.500:1]", "ok"]
        assert sim.position["z"] == pytest.approx(-1.5)


async def test_g43_1_offsets_every_target_until_g49(classic_host: GrblHost) -> None:
    """gnea/grbl gcode.c: G43.1 takes the Z word alone (error:37 otherwise); the WCO
    and every target carry it; G49 cancels it."""
    assert await classic_host.ask(b"G43.1 X1\n") == ["error:37"]
    assert await classic_host.ask(b"G43.1 Z2.5\n") == ["ok"]
    assert await classic_host.ask(b"G0 Z-1\n") == ["ok"]
    assert (await classic_host.ask(b"G4 P0\n")) == ["ok"]
    assert "MPos:0.000,0.000,1.500" in await classic_host.status()
    assert await classic_host.ask(b"G49\n") == ["ok"]
    assert await classic_host.ask(b"G0 Z-1\n") == ["ok"]
    assert await classic_host.ask(b"G4 P0\n") == ["ok"]
    assert "MPos:0.000,0.000,-1.000" in await classic_host.status()


async def test_probe_already_touching_is_alarm_4(
    hal_host: GrblHost, hal: GrblSimController
) -> None:
    hal.probe(True)
    assert await hal_host.ask(b"G38.2 Z-10 F600\n") == ["ALARM:4", "ok"]


async def test_a_touch_plate_ends_the_probe_at_its_top_face(
    hal_host: GrblHost, hal: GrblSimController
) -> None:
    hal.touch_plate(TouchPlate(top=-2.5))
    assert await hal_host.ask(b"G38.2 Z-10 F600\n") == ["[PRB:0.000,0.000,-2.500:1]", "ok"]
    assert "Pn:P" in await hal_host.status()  # the bit rests on the plate


async def test_a_probe_that_misses_the_plate_is_alarm_5(
    classic_host: GrblHost, classic: GrblSimController
) -> None:
    classic.touch_plate(TouchPlate(top=-20.0))
    got = await classic_host.ask(b"G38.2 Z-10 F600\n")
    assert got == ["ALARM:5", "[PRB:0.000,0.000,0.000:0]", "ok"]
    assert classic.position["z"] == -10  # where the board stopped
    assert classic.state == "Alarm"


async def test_a_miss_reports_where_it_stopped_on_hal_and_after_a_g38_3(
    classic_host: GrblHost, classic: GrblSimController, hal_host: GrblHost
) -> None:
    """Classic copies the position after a miss only for G38.3/.5 (motion_control.c:297);
    grblHAL after any (motion_control.c:1105)."""
    assert await hal_host.ask(b"G38.2 Z-10 F600\n") == [
        "ALARM:5",
        "[PRB:0.000,0.000,-10.000:0]",
        "ok",
    ]
    assert await classic_host.ask(b"G38.3 Z-4 F600\n") == ["[PRB:0.000,0.000,-4.000:0]", "ok"]
    assert classic.state == "Idle"  # no alarm: the no-error probe


async def test_a_corner_plates_wall_meets_the_bit_by_its_radius(
    hal_host: GrblHost, hal: GrblSimController
) -> None:
    hal.touch_plate(TouchPlate(top=-10.0, x_face=20.0, y_face=30.0, tool_radius=1.5))
    assert await hal_host.ask(b"G0 X25 Z-12\n") == ["ok"]  # over the plate in X, beside it in Y
    assert await hal_host.ask(b"G38.2 Y40 F600\n") == ["[PRB:25.000,28.500,-12.000:1]", "ok"]


async def test_the_operator_touching_the_plate_shows_pn_p(
    hal_host: GrblHost, hal: GrblSimController
) -> None:
    assert "Pn" not in await hal_host.status()
    hal.touch(reads=1)
    assert "Pn:P" in await hal_host.status()
    assert "Pn" not in await hal_host.status()  # let go


async def test_check_mode(classic_host: GrblHost, classic: GrblSimController) -> None:
    assert await classic_host.ask(b"$C\n") == ["[MSG:Enabled]", "ok"]
    assert await classic_host.ask(b"G0 X-50\n") == ["ok"]
    assert (await classic_host.status()).startswith("<Check|MPos:0.000,0.000,0.000")
    assert await classic_host.ask(b"$C\n") == ["[MSG:Disabled]", "ok"]
    assert (await classic_host.until(lambda s: s.startswith("Grbl ")))[-1].startswith("Grbl 1.1h")
    assert classic.state == "Idle"


# --- status reports


async def test_grblhal_status_report_fields(hal_host: GrblHost) -> None:
    first = await hal_host.status()
    assert first == "<Idle|MPos:0.000,0.000,0.000|Bf:100,1023|FS:0,0|Ov:100,100,100>"
    second = await hal_host.status()
    assert second == "<Idle|MPos:0.000,0.000,0.000|Bf:100,1023|FS:0,0|WCO:0.000,0.000,0.000>"
    third = await hal_host.status()
    assert third == "<Idle|MPos:0.000,0.000,0.000|Bf:100,1023|FS:0,0>"


async def test_classic_status_report_fields(classic_host: GrblHost) -> None:
    first = await classic_host.status()
    assert first == "<Idle|MPos:0.000,0.000,0.000|FS:0,0|WCO:0.000,0.000,0.000>"
    assert await classic_host.status() == "<Idle|MPos:0.000,0.000,0.000|FS:0,0|Ov:100,100,100>"
    assert await classic_host.status() == "<Idle|MPos:0.000,0.000,0.000|FS:0,0>"


async def test_grblhal_says_the_accessories_on_the_report_after_they_change(
    hal_host: GrblHost,
) -> None:
    """`A:` on the next report after M3, M8 or M5 M9, even empty (spindle_control.c:750,
    coolant_control.c:37, report.c:1475-1505), not only with an Ov refresh: so the host
    sees the spindle start before the refresh comes round."""
    await hal_host.status()  # the first report's Ov refresh is over
    hal_host.send(b"M3 S500\n")
    await hal_host.until(is_answer)
    assert (await hal_host.status()).endswith("|A:S>")
    assert "|A:" not in await hal_host.status()  # told once
    hal_host.send(b"M8\n")
    await hal_host.until(is_answer)
    assert (await hal_host.status()).endswith("|A:SF>")
    hal_host.send(b"M5 M9\n")
    await hal_host.until(is_answer)
    assert (await hal_host.status()).endswith("|A:>")


async def test_classic_says_the_accessories_only_with_its_ov_refresh(
    classic_host: GrblHost,
) -> None:
    """gnea/grbl report.c:620-640: `A:` rides with `Ov:`, and is left out when none is on."""
    classic_host.send(b"M3 S500\n")
    await classic_host.until(is_answer)
    reports = [await classic_host.status() for _ in range(12)]
    told = [r for r in reports if "|A:" in r]
    assert told and all("|Ov:" in r and r.endswith("|A:S>") for r in told)


async def test_status_is_not_answered_while_homing(tmp_path: Path) -> None:
    config = replace(TIMED_HAL, homing=True)
    async with Board(tmp_path, config) as (sim, host):
        host.send(b"$H\n")
        assert (await host.line()).startswith("<Home|MPos:0.000")  # forced as homing starts
        await sim.wait_state("Home")
        host.send(b"??")
        got = await host.until(is_answer)
        assert got[0].startswith("<Home|MPos:-1.000,-1.000,-1.000")  # one, at the end
        assert got[1:] == ["[MSG:]", "ok"]


async def test_grblhal_reports_before_the_overrides_read_with_the_request_act(
    hal_host: GrblHost,
) -> None:
    """One USB packet: protocol_exec_rt_system prints the report, then runs the overrides."""
    await hal_host.status()
    await hal_host.status()
    hal_host.send(b"\x91\x91\x96?")  # one write, one read
    before = (await hal_host.until(lambda s: s.startswith("<")))[-1]
    assert before.startswith("<Idle|") and "Ov:120" not in before
    assert "|Ov:120,50,100" in await hal_host.status()  # the next report shows them


async def test_classic_grbl_counts_alike_overrides_read_together_once(
    classic_host: GrblHost,
) -> None:
    """The receive interrupt sets one flag bit per kind and the main loop applies them once
    a pass (serial.c:167-181, protocol.c:405-452): a reset, three "+10" and two "+1" read
    together make 111. A `?` behind them came a pass later (a UART brings a byte at a
    time): it reports them. Read apart, each acts."""
    await classic_host.status()
    classic_host.send(b"\x90\x91\x91\x91\x93\x93\x96?")
    assert "|Ov:111,50,100" in (await classic_host.until(lambda s: s.startswith("<")))[-1]
    for feed in (121, 131):
        classic_host.send(b"\x91?")
        assert f"|Ov:{feed},50,100" in (await classic_host.until(lambda s: s.startswith("<")))[-1]


async def test_classic_grbl_reports_no_ov_for_overrides_that_change_nothing(
    classic_host: GrblHost,
) -> None:
    """`Ov:` is forced into the next report only when a value changed (protocol.c:427,
    :452); otherwise it comes when report.c's counter runs out (one in 10 at rest)."""
    await classic_host.status()
    assert "|Ov:" in await classic_host.status()
    classic_host.send(b"\x90\x95\x99?")  # all at 100 already
    assert "|Ov:" not in (await classic_host.until(lambda s: s.startswith("<")))[-1]
    classic_host.send(b"\x94?")
    assert "|Ov:99,100,100" in (await classic_host.until(lambda s: s.startswith("<")))[-1]


async def test_grblhal_drops_override_bytes_that_find_their_ring_full(tmp_path: Path) -> None:
    """Rings of 16 slots, 15 usable (override.h, override.c:35-43), feed and rapid in one,
    spindle in another (protocol.c:941-960), emptied once a pass: of 20 feed bytes read
    together the last 5 are lost, and the 15 spindle bytes all fit."""
    async with Board(tmp_path, HAL) as (sim, host):
        await host.status()
        # Rapid 25, 19 of "+1", 15 of spindle "+1", and a `?`: one write, one read. The
        # report comes first (report_first); the next one shows them.
        host.send(b"\x97" + b"\x93" * 19 + b"\x9c" * 15 + b"?")
        await host.until(lambda s: s.startswith("<"))
        assert "|Ov:114,25,115" in await host.status()
        assert sim.board.ovr_dropped == 5
        host.send(b"\x93" * 5 + b"?")  # the ring is empty again: all five fit
        await host.until(lambda s: s.startswith("<"))
        assert "|Ov:119,25,115" in await host.status()
        assert sim.board.ovr_dropped == 5


async def test_grblhal_answers_the_requests_of_one_packet_with_one_report(
    hal_host: GrblHost,
) -> None:
    """Each `?` only sets the EXEC_STATUS_REPORT bit (grblHAL protocol.c:871-875) and a
    pass prints one report (:604-605): `???` in one packet is one report."""
    await hal_host.status()
    hal_host.send(b"???")
    hal_host.send(b"$G\n")  # answered after the pass that read the `?`s
    lines = await hal_host.until(lambda s: s == "ok")
    assert sum(line.startswith("<") for line in lines) == 1


async def test_input_queued_in_the_transport_is_read_a_byte_a_pass(tmp_path: Path) -> None:
    """`queue_input`: nothing is read meanwhile; then a byte a pass, in order, as the
    upstream grblHAL Simulator feeds its firmware: each `?` gets its own report, and
    one behind an override byte shows it (the byte acted in its own, earlier pass)."""
    async with Board(tmp_path, HAL) as (sim, host):
        await host.status()
        sim.queue_input()
        host.send(b"??\x91?")
        await sim.wait_for(lambda: sim.board.queued == b"??\x91?")
        sim.queue_input(False)
        reports = [await host.line() for _ in range(3)]
        assert all(r.startswith("<") for r in reports)
        assert "|Ov:" not in reports[1] and "|Ov:110,100,100" in reports[2]


async def test_grblhal_answers_a_request_read_with_its_resume_still_holding(
    tmp_path: Path,
) -> None:
    """`~?` in one packet: the report says Hold (state_update runs after it), then the
    board resumes; the host's session asks again (RESUME_ASKS)."""
    async with Board(tmp_path, TIMED_HAL) as (sim, host):
        assert await host.ask(b"G1 X-3 F600\n") == ["ok"]
        await sim.wait_state("Run")
        host.send(b"!")
        await sim.wait_state("Hold:0")
        host.send(b"~?")
        assert (await host.until(lambda s: s.startswith("<")))[-1].startswith("<Hold:0|")
        await sim.wait_state("Idle")
        assert sim.position["x"] == -3


# --- silence: homing, EEPROM and flash, lost and unanswered `?`


async def test_classic_homing_prints_nothing_until_the_cycle_ends(tmp_path: Path) -> None:
    config = replace(TIMED_CLASSIC, homing=True, homing_time=0.3)
    async with Board(tmp_path, config) as (sim, host):
        host.send(b"$X\n")
        await host.until(is_answer)
        host.send(b"$H\n")
        await sim.wait_state("Home")
        host.send(b"?")  # limits_go_home serves no `?`: it waits out the cycle
        got = await host.until(is_answer)
        assert got[0].startswith("<Home|MPos:-1.000,-1.000,-1.000")
        assert got[1:] == ["ok"]  # no forced report before it, no [MSG:] after (classic)


async def test_a_grblhal_build_without_the_forced_home_report(tmp_path: Path) -> None:
    config = replace(TIMED_HAL, homing=True, hal_home_report=False)
    async with Board(tmp_path, config) as (sim, host):
        host.send(b"$H\n")
        await sim.wait_state("Home")
        got = await host.until(is_answer)
        assert got == ["[MSG:]", "ok"]  # COMPATIBILITY_LEVEL > 0: not a report in the cycle


async def test_homing_time_is_the_machines_divided_by_the_speed_factor(tmp_path: Path) -> None:
    # A cycle of 30 s on the machine, 0.3 s here: the board is in Home for all of it.
    config = replace(TIMED_CLASSIC, homing=True, homing_time=30.0, speed_factor=100.0)
    async with Board(tmp_path, config) as (sim, host):
        await host.ask(b"$X\n")
        host.send(b"$H\n")
        await sim.wait_state("Home")
        assert await host.until(is_answer) == ["ok"]
        assert sim.state == "Idle" and sim.board.homed


async def test_classic_grbl_loses_bytes_while_it_writes_its_eeprom(tmp_path: Path) -> None:
    config = replace(TIMED_CLASSIC, storage_write=0.3)
    async with Board(tmp_path, config) as (sim, host):
        host.send(b"$110=600\n")
        await sim.wait_for(lambda: sim.board._deaf_until is not None)
        host.send(b"?G1 X-1 F600\n")  # arrives during the write, interrupts off: lost
        assert await host.until(is_answer) == ["ok"]
        await sim.wait_for(lambda: sim.board.lost_in_write > 0)
        assert sim.board.settings[110] == 600
        assert await host.ask(b"$110\n") == ["$110=600.000", "ok"]  # the next line is fine
        assert sim.position["x"] == 0  # the move was never read


async def test_classic_syncs_then_writes_offsets_with_g10(tmp_path: Path) -> None:
    config = replace(TIMED_CLASSIC, storage_write=0.2)
    async with Board(tmp_path, config) as (sim, host):
        assert await host.ask(b"G1 X-1 F600\n") == ["ok"]
        host.send(b"G10 L20 P1 X0\n")
        await sim.wait_state("Run")
        await sim.wait_for(lambda: sim.board._deaf_until is not None, timeout=3)
        assert sim.state == "Idle" and sim.position["x"] == -1  # the planner emptied first
        assert await host.until(is_answer) == ["ok"]


async def test_grblhal_answers_then_writes_flash_keeping_what_arrives(tmp_path: Path) -> None:
    config = replace(TIMED_HAL, storage_write=0.3)
    async with Board(tmp_path, config) as (sim, host):
        assert await host.ask(b"$110=600\n") == ["ok"]  # the answer first
        await sim.wait_for(lambda: sim.board._deaf_until is not None)
        host.send(b"?")  # held by the USB stack meanwhile
        report = await host.line()
        assert report.startswith("<Idle|") and sim.board._deaf_until is None


async def test_a_lost_status_request_gets_no_report(
    classic_host: GrblHost, classic: GrblSimController
) -> None:
    classic.lose_status_requests(1)
    classic_host.send(b"?")
    assert await classic_host.ask(b"G4 P0\n") == ["ok"]  # only the answer: `?` was lost
    assert (await classic_host.status()).startswith("<Idle|")


async def test_oks_go_on_while_status_requests_are_ignored(
    classic_host: GrblHost, classic: GrblSimController
) -> None:
    classic.ignore_status_requests()
    for _ in range(5):
        classic_host.send(b"?")
        assert await classic_host.ask(b"G4 P0\n") == ["ok"]
    classic.ignore_status_requests(False)
    assert (await classic_host.status()).startswith("<Idle|")


async def test_a_hung_board_says_nothing(
    classic_host: GrblHost, classic: GrblSimController
) -> None:
    classic.hang()
    classic_host.send(b"?$$\n")
    with pytest.raises(TimeoutError):
        await classic_host.line(timeout=0.3)
    classic.hang(False)
    assert (await classic_host.status()).startswith("<Idle|")


@pytest.mark.parametrize(
    ("config", "answered"), [(TIMED_CLASSIC, True), (TIMED_HAL, False)], ids=["grbl", "grblhal"]
)
async def test_lines_are_planned_while_a_hold_decelerates_on_classic_grbl_only(
    tmp_path: Path, config: GrblConfig, answered: bool
) -> None:
    slow = replace(config, feedhold_decel=0.5)
    async with Board(tmp_path, slow) as (sim, host):
        assert await host.ask(b"G1 X-10 F600\n") == ["ok"]
        await sim.wait_state("Run")
        host.send(b"!")
        await sim.wait_state("Hold:1")
        host.send(b"G1 X-2 F600\n")
        if answered:  # protocol.c: not suspended until the deceleration is over
            assert await host.until(is_answer, timeout=0.4) == ["ok"]
        else:  # state_machine.c initiate_hold: suspended at once
            with pytest.raises(TimeoutError):
                await host.line(timeout=0.3)
        await sim.wait_state("Hold:0")
        host.send(b"G4 P0\n")
        with pytest.raises(TimeoutError):  # a complete hold reads nothing on either
            await host.line(timeout=0.3)
        host.send(b"~")
        assert await host.until(is_answer) == ["ok"]  # read again once resumed


# --- startup blocks ($N), system.c system_execute_startup


async def test_startup_blocks_are_stored_listed_and_run_after_a_reset(
    classic_host: GrblHost, classic: GrblSimController
) -> None:
    assert await classic_host.ask(b"$N\n") == ["$N0=", "$N1=", "ok"]
    # Storing runs the block once to prove it valid (system.c: gc_execute_line).
    assert await classic_host.ask(b"$N0=g0 x-5\n") == ["ok"]
    assert await classic_host.ask(b"$N1=G1X1\n") == ["error:22"]  # no feed: not stored
    assert await classic_host.ask(b"$N\n") == ["$N0=G0X-5", "$N1=", "ok"]
    assert await classic_host.ask(b"G0X0\n") == ["ok"]
    classic_host.send(b"\x18")
    got = await classic_host.until(lambda s: s.startswith(">"))
    assert got[-2:] == ["Grbl 1.1h ['$' for help]", ">G0X-5:ok"]  # report_execute_startup_message
    await classic.wait_for(lambda: classic.board.position["x"] == -5.0)
