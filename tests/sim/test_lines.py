"""Lines in, responses out: one `{r}` per line, its byte count, and the planner's pace."""

from __future__ import annotations

from pathlib import Path

import pytest

from hostd.sim import SimConfig, SimController

from .conftest import INSTANT, TIMED, Host, has_stat, responses

pytestmark = pytest.mark.asyncio


async def test_every_line_gets_exactly_one_response_with_its_byte_count(host: Host) -> None:
    assert (await host.ask(b"G21 G90 F600\n"))["f"] == [1, 0, 13]  # data: chars + 1
    assert (await host.ask(b'{"gc":"G1 X0"}\n'))["f"] == [1, 0, 16]  # control: + terminator
    host.send(b"\n\r\n\n")  # empty lines produce nothing
    assert (await host.ask(b"{xvm:n}\r\n")) == {"r": {"xvm": 6000}, "f": [1, 0, 10]}
    assert (await host.ask(b"$xtm\r")) == {"r": {"xtm": 300}, "f": [1, 0, 5]}


async def test_a_control_line_counts_the_terminators_that_came_with_it(host: Host) -> None:
    assert (await host.ask(b"{xvm:n}\r\n\n"))["f"] == [1, 0, 11]


async def test_json_line_jumps_the_queue_of_data_lines(tmp_path: Path) -> None:
    config = SimConfig(planner_depth=1, status_interval=0.02)
    async with SimController(str(tmp_path / "tty"), config=config) as sim:
        host = await Host.open(sim.data_path)
        try:
            host.send(b"G1 X1 F60\nG1 X2\n")  # the first move lasts a second
            assert (await host.response())["f"] == [1, 0, 10]
            await sim.wait_received(b"G1 X2")  # waiting: the planner is full
            host.send(b"{qr:n}\n")
            assert (await host.response()) == {"r": {"qr": 0}, "f": [1, 0, 8]}
        finally:
            await host.close()


async def test_a_full_planner_holds_back_responses_until_moves_finish(tmp_path: Path) -> None:
    depth = 4
    config = SimConfig(planner_depth=depth, status_interval=0.02)
    async with SimController(str(tmp_path / "tty"), config=config) as sim:
        host = await Host.open(sim.data_path)
        try:
            host.send(b"G1 X1 F300\n")  # 1 mm at 300 mm/min: 0.2 s
            lines = [f"G1 X{i + 2}".encode() for i in range(depth + 2)]
            host.send(b"".join(line + b"\n" for line in lines))
            await sim.wait_for(lambda: sum(r.kind == "line" for r in sim.received) == depth + 3)
            await sim.wait_for(lambda: sim.planner_len == depth)
            answered = [s for s in sim.sent if s.data.startswith(b'{"r"')]
            assert len(answered) == 1 + depth  # banner + the lines the planner took
            assert sim.position["x"] < 1.0  # the first move is still running
            got = await host.until(lambda m: "r" in m)
            while len(responses(got)) < depth + 1:
                got += await host.until(lambda m: "r" in m)
            assert sim.position["x"] >= 1.0  # answered only once a move had finished
        finally:
            host.send(b"\x04")
            await host.close()


async def test_a_percent_line_outside_a_hold_gets_no_response(host: Host) -> None:
    host.send(b"%\n$xvm\n")
    response = await host.response()
    assert response == {"r": {"xvm": 6000}, "f": [1, 0, 5]}


async def test_a_nul_byte_discards_the_lines_waiting_in_the_buffer(tmp_path: Path) -> None:
    config = SimConfig(planner_depth=1, status_interval=0.02)
    async with SimController(str(tmp_path / "tty"), config=config) as sim:
        host = await Host.open(sim.data_path)
        try:
            host.send(b"G1 X1 F200\n")  # 0.3 s in the planner
            host.send(b"G1 X2\nG1 X3\n")  # wait in the RX buffer: the planner is full
            await sim.wait_received(b"G1 X3")
            host.send(b"\x00G1 X4\n")  # the NUL and the rest of its chunk go too
            await sim.wait_for(lambda: sim.planner_len == 0)
            host.send(b"$xvm\n")
            got = responses(await host.until(lambda m: m.get("f", [0, 0, 0])[2] == 5))
            assert [r["f"][2] for r in got] == [11, 5]
            assert sim.position["x"] == pytest.approx(1.0)
        finally:
            await host.close()


async def test_an_overlong_line_is_cut_at_511_characters(host: Host) -> None:
    host.send(b"(" + b"a" * 700 + b")\n$xvm\n")
    got = responses(await host.until(lambda m: m.get("f", [0, 0, 0])[2] == 5))
    assert [r["f"] for r in got] == [[1, 0, 512], [1, 0, 5]]


async def test_line_numbers_are_echoed_from_json_verbosity_4(host: Host) -> None:
    assert (await host.ask(b"N7 G0 X1\n"))["r"] == {}
    assert (await host.ask(b"{jv:4}\n"))["r"] == {"jv": 4}
    assert (await host.ask(b"N8 G0 X2\n")) == {"r": {"n": 8}, "f": [1, 0, 9]}
    assert (await host.ask(b"G0 X3\n"))["r"] == {}


async def test_errors_carry_g2core_status_codes(host: Host) -> None:
    assert (await host.ask(b"{bogus:n}\n")) == {"r": {"bogus": None}, "f": [1, 100, 11]}
    assert (await host.ask(b"{xvm:\n")) == {"r": {"err": "{xvm:"}, "f": [1, 111, 7]}
    assert (await host.ask(b"G1 X5\n"))["f"][1] == 142  # no feed rate yet
    assert (await host.ask(b"G33 Z-1\n"))["f"][1] == 131
    assert (await host.ask(b"M100\n"))["f"][1] == 132
    assert (await host.ask(b"{fb:100}\n"))["f"][1] == 104


async def test_relaxed_json_gets_and_sets(host: Host) -> None:
    assert (await host.ask(b"{XVM:1234}\n"))["r"] == {"xvm": 1234}
    assert (await host.ask(b'{"xvm":""}\n'))["r"] == {"xvm": 1234}
    assert (await host.ask(b"{sl:f}\n"))["r"] == {"sl": 0}
    assert (await host.ask(b"{xvm:null,yvm:n}\n"))["r"] == {"xvm": 1234, "yvm": 6000}


async def test_status_report_list_is_replaced_and_reported_on_request(host: Host) -> None:
    answer = await host.ask(b"{sr:{stat:t,posx:t}}\n")
    assert answer["r"] == {"sr": {"stat": 1, "posx": 0}}
    assert (await host.ask(b"{sr:n}\n"))["r"] == {"sr": {"stat": 1, "posx": 0}}
    assert (await host.ask(b"?\n")) == {"r": {"sr": {"stat": 1, "posx": 0}}, "f": [1, 0, 2]}
    assert (await host.ask(b"{sr:{stat:f}}\n"))["f"][1] == 103


async def test_status_reports_follow_every_state_change(host: Host) -> None:
    host.send(b"G1 X5 F1000\n")
    got = await host.until(has_stat(3))
    reports = [m["sr"] for m in got if "sr" in m]
    assert [r["stat"] for r in reports if "stat" in r] == [5, 3]
    assert [r["posx"] for r in reports if "posx" in r][-1] == 5


async def test_status_reports_show_motion_while_a_move_runs(timed_host: Host) -> None:
    timed_host.send(b"{sr:{posx:t,vel:t,stat:t}}\nG1 X1 F300\n")  # 0.2 s
    got = await timed_host.until(has_stat(3))
    xs = [m["sr"]["posx"] for m in got if "posx" in m.get("sr", {})]
    assert any(0 < x < 1 for x in xs)
    assert any(m["sr"].get("vel") == 300 for m in got if "sr" in m)


async def test_units_and_offsets_show_in_work_position(host: Host) -> None:
    host.send(b"G0 X10\nG92 X0\nG20\nG0 X1\n")
    await host.until(has_stat(3))
    report = (await host.ask(b"?\n"))["r"]["sr"]
    assert report["unit"] == 0
    assert report["posx"] == 1
    await host.ask(b"G21\n")
    assert (await host.ask(b"{mpox:n}\n"))["r"] == {"mpox": 35.4}


async def test_per_open_settings_reset_and_the_rest_survive(sim: SimController) -> None:
    host = await Host.open(sim.data_path)
    await host.ask(b"{jv:4}\n")
    await host.ask(b"{sv:0}\n")
    await host.ask(b"{qv:1}\n")
    await host.close()
    host = await Host.open(sim.data_path)
    try:
        assert (await host.ask(b"{sv:n}\n"))["r"] == {"sv": 1}
        assert (await host.ask(b"{qv:n}\n"))["r"] == {"qv": 0}
        assert (await host.ask(b"{jv:n}\n"))["r"] == {"jv": 4}
    finally:
        await host.close()


async def test_response_delay_holds_back_only_data_lines(tmp_path: Path) -> None:
    async with SimController(str(tmp_path / "tty"), config=INSTANT) as sim:
        host = await Host.open(sim.data_path)
        try:
            sim.set_ack_delay(0.2)
            host.send(b"$xvm\n{yvm:n}\n")
            first = await host.response()
            assert first["r"] == {"yvm": 6000}  # the control line was not delayed
            second = await host.response()
            assert second["r"] == {"xvm": 6000}
        finally:
            await host.close()


async def test_many_lines_per_second_in_instant_mode(tmp_path: Path) -> None:
    async with SimController(str(tmp_path / "tty"), config=INSTANT) as sim:
        host = await Host.open(sim.data_path)
        try:
            total, window, sent, acked = 2000, 8, 0, 0
            while acked < total:
                while sent < total and sent - acked < window:
                    host.send(f"G1 X{sent % 100} Y{sent % 7} F3000\n".encode())
                    sent += 1
                if "r" in await host.message():
                    acked += 1
            await sim.wait_for(lambda: sim.planner_len == 0)
        finally:
            await host.close()


async def test_timed_moves_take_their_time(tmp_path: Path) -> None:
    async with SimController(str(tmp_path / "tty"), config=TIMED) as sim:
        host = await Host.open(sim.data_path)
        try:
            host.send(b"G1 X1 F600\n")  # 0.1 s
            await host.until(has_stat(3))
            assert sim.position["x"] == pytest.approx(1.0)
        finally:
            await host.close()
