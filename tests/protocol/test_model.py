"""The machine model follows what the controller reports."""

from __future__ import annotations

from hostd.protocol.messages import ExceptionReport
from hostd.protocol.model import MachineModel
from hostd.protocol.parser import parse_line
from hostd.protocol.states import MachineState


def report(raw: bytes) -> ExceptionReport:
    msg = parse_line(raw)
    assert isinstance(msg, ExceptionReport)
    return msg


def test_status_report_updates_the_snapshot() -> None:
    model = MachineModel("mill")
    changed = model.apply_status(
        {"stat": 5, "posx": 1.5, "posy": -2, "line": 12, "vel": 600.0, "feed": 800, "unit": 1}
    )
    assert changed is MachineState.RUN
    snap = model.snapshot()
    assert snap["state"] == {"code": 5, "name": "RUN"}
    assert snap["position"] == {"x": 1.5, "y": -2.0}
    assert (snap["line"], snap["velocity"], snap["feed"], snap["units"]) == (12, 600.0, 800.0, "mm")


def test_filtered_reports_only_change_what_they_carry() -> None:
    model = MachineModel("mill")
    model.apply_status({"stat": 5, "posx": 1.0, "posy": 2.0})
    assert model.apply_status({"posx": 3.0}) is None
    assert model.position == {"x": 3.0, "y": 2.0}
    assert model.state is MachineState.RUN


def test_nonsense_values_are_ignored_not_stored() -> None:
    model = MachineModel("mill")
    model.apply_status({"stat": 99, "posx": "far", "vel": True, "unit": 7})
    assert model.state is None
    assert model.position == {}
    assert model.velocity is None
    assert model.units is None


def test_shutdown_unhomes() -> None:
    model = MachineModel("mill", homed=True)
    model.apply_status({"stat": 12})
    assert model.homed is False


def test_limit_switch_alarm_unhomes_and_is_kept_as_last_exception() -> None:
    model = MachineModel("mill", homed=True)
    model.apply_exception(report(b'{"er":{"fb":101.06,"st":203,"msg":"Limit hit - input 1"}}'))
    assert model.homed is False
    assert model.snapshot()["last_exception"] == {
        "fb": 101.06,
        "st": 203,
        "msg": "Limit hit - input 1",
    }


def test_soft_limit_alarm_keeps_homing() -> None:
    model = MachineModel("mill", homed=True)
    model.apply_exception(report(b'{"er":{"fb":101.06,"st":221,"msg":"Soft limit"}}'))
    assert model.homed is True


def test_reset_forgets_the_controller() -> None:
    model = MachineModel("mill")
    model.apply_status({"stat": 1, "posx": 4.0, "unit": 0})
    model.reset()
    assert model.snapshot()["state"] is None
    assert model.position == {}
