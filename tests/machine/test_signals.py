"""Signals: `[machines.signals]` config, evaluating filtered reports, the faults they make."""

from __future__ import annotations

import re
import textwrap
import tomllib
from typing import Any

import pytest
from pydantic import ValidationError

from hostd.machine import signals as signals_module
from hostd.machine.signals import SignalsConfig, Source, fault_conditions

LID_AND_BOTH_LASERS = {
    "lid_open": {"key": "in4", "equals": 1},
    "main_laser": {"key": "in5", "equals": True},
    "visible_laser": {"key": "in6", "equals": 1},
}


def config(**signals: Any) -> SignalsConfig:
    return SignalsConfig.model_validate(signals)


def error_text(exc: pytest.ExceptionInfo[ValidationError]) -> str:
    return str(exc.value)


# --- validation


def test_no_signals_is_a_valid_config() -> None:
    empty = SignalsConfig()
    assert empty.keys() == []
    assert empty.evaluate({"in4": 1}, {}) == {}
    assert fault_conditions(empty.evaluate({}, {})) == {}


@pytest.mark.parametrize(
    "source",
    [
        {"key": "in4", "equals": 1},
        {"key": "in4", "equals": True},
        {"key": "ain1", "above": 30},
        {"key": "ain1", "below": 1.5},
        {"key": "ain1", "above": 30, "hysteresis": 1},
        {"key": "posx", "below": -2},
        {"key": "abcdefgh", "equals": 0},
    ],
)
def test_a_source_with_one_condition_is_valid(source: dict[str, Any]) -> None:
    Source.model_validate(source)


def test_a_source_without_a_condition_is_refused() -> None:
    with pytest.raises(ValidationError) as err:
        Source.model_validate({"key": "in4"})
    assert "give exactly one condition of equals, above, below (got none)" in error_text(err)


def test_a_source_with_two_conditions_is_refused() -> None:
    with pytest.raises(ValidationError) as err:
        Source.model_validate({"key": "ain1", "above": 30, "below": 10})
    assert "(got above and below)" in error_text(err)


def test_hysteresis_needs_a_threshold() -> None:
    with pytest.raises(ValidationError, match="hysteresis goes with above or below"):
        Source.model_validate({"key": "in4", "equals": 1, "hysteresis": 0.5})
    with pytest.raises(ValidationError):
        Source.model_validate({"key": "ain1", "above": 1, "hysteresis": -0.5})


@pytest.mark.parametrize("key", ["IN4", "in 4", "4in", "", "abcdefghi", "in-4", "sr.in4"])
def test_a_key_must_be_a_short_lower_case_identifier(key: str) -> None:
    with pytest.raises(ValidationError, match="key"):
        Source.model_validate({"key": key, "equals": 1})


@pytest.mark.parametrize(
    "source",
    [
        {"key": "in4", "equals": "1"},
        {"key": "ain1", "above": "30"},
        {"key": "ain1", "above": True},
        {"key": "ain1", "below": float("nan")},
        {"key": "ain1", "above": float("inf")},
    ],
)
def test_conditions_are_numbers_not_text(source: dict[str, Any]) -> None:
    with pytest.raises(ValidationError):
        Source.model_validate(source)


def test_unknown_signals_and_fields_are_refused() -> None:
    with pytest.raises(ValidationError, match="smoke"):
        config(smoke={"key": "in1", "equals": 1})
    with pytest.raises(ValidationError, match="invert"):
        config(estop={"key": "in1", "equals": 1, "invert": True})


def test_lid_open_needs_a_laser() -> None:
    with pytest.raises(ValidationError, match="lid_open needs main_laser"):
        config(lid_open={"key": "in4", "equals": 1})


@pytest.mark.parametrize("laser", ["main_laser", "visible_laser"])
def test_a_laser_without_a_lid_is_refused(laser: str) -> None:
    with pytest.raises(ValidationError, match="used only with lid_open"):
        config(**{laser: {"key": "in5", "equals": 1}})


# --- the module docstring's TOML examples are real configs


def docstring_examples() -> list[str]:
    doc = signals_module.__doc__ or ""
    blocks = re.findall(r"::\n\n((?:    .*\n|\n)+)", doc)
    return [textwrap.dedent(block) for block in blocks]


def test_the_documented_examples_are_valid() -> None:
    examples = docstring_examples()
    assert len(examples) == 2
    for text in examples:
        machine = tomllib.loads(text)["machines"][0]
        signals = SignalsConfig.model_validate(machine["signals"])
        assert signals.keys()


# --- keys


def test_keys_lists_each_status_report_key_once_in_signal_order() -> None:
    signals = config(
        **LID_AND_BOTH_LASERS,
        estop={"key": "in8", "equals": 0},
        coolant_flow_low={"key": "ain1", "below": 1.5},
        coolant_temp_high={"key": "ain1", "above": 40},  # one probe, two thresholds
    )
    assert signals.keys() == ["in8", "in4", "in5", "in6", "ain1"]


# --- evaluate


def test_a_binary_signal_equals_its_value() -> None:
    signals = config(estop={"key": "in8", "equals": 0})
    assert signals.evaluate({"in8": 0}, {}) == {"estop": True}
    assert signals.evaluate({"in8": 1}, {}) == {"estop": False}


def test_true_and_one_are_the_same_value() -> None:
    on_true = config(estop={"key": "in8", "equals": True})
    on_one = config(estop={"key": "in8", "equals": 1})
    for signals in (on_true, on_one):
        assert signals.evaluate({"in8": 1}, {}) == {"estop": True}
        assert signals.evaluate({"in8": True}, {}) == {"estop": True}
        assert signals.evaluate({"in8": 1.0}, {}) == {"estop": True}
        assert signals.evaluate({"in8": 0}, {}) == {"estop": False}
        assert signals.evaluate({"in8": False}, {}) == {"estop": False}


def test_above_is_strictly_above() -> None:
    signals = config(coolant_temp_high={"key": "ain2", "above": 28})
    assert signals.evaluate({"ain2": 28}, {}) == {"coolant_temp_high": False}
    assert signals.evaluate({"ain2": 28.01}, {}) == {"coolant_temp_high": True}


def test_below_is_strictly_below() -> None:
    signals = config(coolant_flow_low={"key": "ain1", "below": 1.5})
    assert signals.evaluate({"ain1": 1.5}, {}) == {"coolant_flow_low": False}
    assert signals.evaluate({"ain1": 1.49}, {}) == {"coolant_flow_low": True}
    assert signals.evaluate({"ain1": -3}, {}) == {"coolant_flow_low": True}


def test_a_binary_flow_switch_works_too() -> None:
    signals = config(coolant_flow_low={"key": "in6", "equals": 0})
    assert signals.evaluate({"in6": 0}, {}) == {"coolant_flow_low": True}
    assert signals.evaluate({"in6": 1}, {}) == {"coolant_flow_low": False}


def test_hysteresis_holds_an_active_threshold_signal() -> None:
    signals = config(coolant_temp_high={"key": "ain2", "above": 28, "hysteresis": 1})
    state: dict[str, bool] = {}
    readings = [27.5, 28.5, 27.5, 27.01, 27.0, 27.9, 28.1]
    seen = []
    for reading in readings:
        state = signals.evaluate({"ain2": reading}, state)
        seen.append(state["coolant_temp_high"])
    assert seen == [False, True, True, True, False, False, True]


def test_hysteresis_below() -> None:
    signals = config(coolant_flow_low={"key": "ain1", "below": 1.5, "hysteresis": 0.5})
    assert signals.evaluate({"ain1": 1.7}, {}) == {"coolant_flow_low": False}
    assert signals.evaluate({"ain1": 1.7}, {"coolant_flow_low": True}) == {"coolant_flow_low": True}
    assert signals.evaluate({"ain1": 2.0}, {"coolant_flow_low": True}) == {
        "coolant_flow_low": False
    }


def test_a_key_never_reported_is_inactive() -> None:
    signals = config(
        estop={"key": "in8", "equals": 0},
        coolant_flow_low={"key": "ain1", "below": 1.5},
    )
    assert signals.evaluate({}, {}) == {"estop": False, "coolant_flow_low": False}
    # even when it was active before: unknown is not a fault
    assert signals.evaluate({}, {"estop": True, "coolant_flow_low": True}) == {
        "estop": False,
        "coolant_flow_low": False,
    }


@pytest.mark.parametrize("value", [None, "1", [1], {"v": 1}])
def test_a_value_that_is_not_a_number_is_inactive(value: Any) -> None:
    signals = config(estop={"key": "in8", "equals": 1})
    assert signals.evaluate({"in8": value}, {}) == {"estop": False}


def test_evaluate_with_filtered_reports_carried_over_by_the_caller() -> None:
    signals = config(**LID_AND_BOTH_LASERS, coolant_flow_low={"key": "ain1", "below": 1.5})
    reports: list[dict[str, Any]] = [
        {"stat": 1, "in4": 0, "in5": 1, "in6": 0, "ain1": 2.0},  # the first report: everything
        {"in4": 1},  # the lid opens
        {"posx": 3.2},  # nothing of ours changed
        {"ain1": 0.7},  # flow drops; the lid is still open
        {"in5": 0, "in6": 1},  # laser switched over
        {"in4": 0},  # the lid closes
    ]
    known: dict[str, Any] = {}
    previous: dict[str, bool] = {}
    faults = []
    for report in reports:
        known.update(report)
        previous = signals.evaluate(known, previous)
        faults.append({k for k, on in fault_conditions(previous).items() if on})
    assert faults == [
        set(),
        {"lid_open"},
        {"lid_open"},
        {"lid_open", "water_flow"},
        {"water_flow"},
        {"lid_closed", "water_flow"},
    ]


# --- fault_conditions


@pytest.mark.parametrize(
    ("lid_open", "main_laser", "visible_laser", "expected"),
    [
        (False, False, False, {"lid_open": False, "lid_closed": False}),
        (False, False, True, {"lid_open": False, "lid_closed": True}),
        (False, True, False, {"lid_open": False, "lid_closed": False}),
        (False, True, True, {"lid_open": False, "lid_closed": True}),
        (True, False, False, {"lid_open": False, "lid_closed": False}),
        (True, False, True, {"lid_open": False, "lid_closed": False}),
        (True, True, False, {"lid_open": True, "lid_closed": False}),
        (True, True, True, {"lid_open": True, "lid_closed": False}),
    ],
)
def test_the_lid_and_laser_truth_table(
    lid_open: bool, main_laser: bool, visible_laser: bool, expected: dict[str, bool]
) -> None:
    signals = {"lid_open": lid_open, "main_laser": main_laser, "visible_laser": visible_laser}
    assert fault_conditions(signals) == expected


@pytest.mark.parametrize(
    ("lid_open", "main_laser", "fault"),
    [(True, True, True), (True, False, False), (False, True, False)],
)
def test_lid_open_without_a_visible_laser_has_no_lid_closed_fault(
    lid_open: bool, main_laser: bool, fault: bool
) -> None:
    assert fault_conditions({"lid_open": lid_open, "main_laser": main_laser}) == {"lid_open": fault}


@pytest.mark.parametrize("visible", [True, False])
def test_lid_open_without_a_main_laser_has_no_lid_open_fault(visible: bool) -> None:
    conditions = fault_conditions({"lid_open": False, "visible_laser": visible})
    assert conditions == {"lid_closed": visible}


@pytest.mark.parametrize("on", [True, False])
def test_each_other_signal_is_its_fault(on: bool) -> None:
    assert fault_conditions({"estop": on}) == {"estop": on}
    assert fault_conditions({"coolant_flow_low": on}) == {"water_flow": on}
    assert fault_conditions({"coolant_temp_high": on}) == {"water_temp": on}


def test_every_configured_fault_appears_and_no_other() -> None:
    signals = config(
        **LID_AND_BOTH_LASERS,
        estop={"key": "in8", "equals": 0},
        coolant_flow_low={"key": "ain1", "below": 1.5},
        coolant_temp_high={"key": "ain2", "above": 28},
    )
    conditions = fault_conditions(signals.evaluate({}, {}))
    assert set(conditions) == {"estop", "lid_open", "lid_closed", "water_flow", "water_temp"}
    assert not any(conditions.values())  # nothing reported yet: nothing active
    partial = config(coolant_temp_high={"key": "ain2", "above": 28})
    assert fault_conditions(partial.evaluate({"ain2": 30}, {})) == {"water_temp": True}
