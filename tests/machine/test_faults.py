"""The fault table: behaviour.md "Faults" (seed 001), rule by rule."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from hostd.machine.faults import (
    FAULT_IDS,
    RULES,
    Clears,
    Fault,
    FaultError,
    FaultTable,
    Indicator,
    Severity,
)

T0 = 1_767_225_600.0  # 2026-01-01T00:00:00Z
T0_ISO = "2026-01-01T00:00:00.000Z"
T1 = T0 + 61.5
T1_ISO = "2026-01-01T00:01:01.500Z"

SIGNAL_FAULTS = ["estop", "lid_open", "lid_closed", "water_flow", "water_temp"]
SOFTWARE_FAULTS = ["serial", "lexical", "underflow"]
RESET_FAULTS = ["syntax", "internal"]
OVERRIDABLE = ["lid_open", "lid_closed", "water_flow", "water_temp"]
NOT_OVERRIDABLE = ["estop", "serial", "lexical", "syntax", "underflow", "internal"]


def make_active(table: FaultTable, fault_id: str, now: float = T0) -> Fault | None:
    if RULES[fault_id].clears == Clears.SIGNAL:
        return table.set(fault_id, True, now=now)
    return table.raise_(fault_id, now=now)


# --- the table is behaviour.md's


def test_the_table_has_the_ten_faults_in_behaviour_md_order() -> None:
    assert FAULT_IDS == (
        "estop",
        "lid_open",
        "lid_closed",
        "water_flow",
        "water_temp",
        "serial",
        "lexical",
        "syntax",
        "underflow",
        "internal",
    )
    assert [f.id for f in FaultTable().all()] == list(FAULT_IDS)


@pytest.mark.parametrize(
    ("fault_id", "severity", "overridable", "clears"),
    [
        ("estop", "job", False, Clears.SIGNAL),
        ("lid_open", "job", True, Clears.SIGNAL),
        ("lid_closed", "recoverable", True, Clears.SIGNAL),
        ("water_flow", "hardware", True, Clears.SIGNAL),
        ("water_temp", "hardware", True, Clears.SIGNAL),
        ("serial", "job", False, Clears.SOFTWARE),
        ("lexical", "job", False, Clears.SOFTWARE),
        ("syntax", "job", False, Clears.RESET),
        ("underflow", "job", False, Clears.SOFTWARE),
        ("internal", "job", False, Clears.RESET),
    ],
)
def test_each_fault_has_its_severity_override_flag_and_clear_rule(
    fault_id: str, severity: str, overridable: bool, clears: Clears
) -> None:
    rule = RULES[fault_id]
    assert (rule.severity, rule.overridable, rule.clears) == (severity, overridable, clears)
    fault = FaultTable().get(fault_id)
    assert (fault.severity, fault.overridable) == (severity, overridable)


def test_a_new_table_has_nothing_active_and_shows_normal() -> None:
    table = FaultTable()
    assert table.active() == []
    assert table.blocking() == []
    assert table.indicator() == Indicator.NORMAL
    for fault in table.all():
        assert not fault.active
        assert not fault.overridden
        assert fault.since is None
        assert fault.value is None
        assert fault.message == RULES[fault.id].text


def test_a_fault_object_is_the_api_md_one() -> None:
    table = FaultTable()
    table.raise_("serial", value=1234, now=T0)
    assert table.get("serial").to_json() == {
        "id": "serial",
        "severity": "job",
        "active": True,
        "overridden": False,
        "overridable": False,
        "since": T0_ISO,
        "value": 1234,
        "message": "serial link error after 1234 lines processed",
        "clears": "software",  # added to api.md's: fault.clear ends it
    }


def test_the_message_carries_the_detail_given() -> None:
    table = FaultTable()
    fault = table.raise_("syntax", message="N12 G1 X (status 108)", now=T0)
    assert fault is not None
    assert fault.message == "the controller rejected a line as malformed: N12 G1 X (status 108)"
    fault = table.set("water_temp", True, value=31.5, now=T0)
    assert fault is not None
    assert fault.message == "coolant temperature high (31.5)"


# --- signal faults follow their condition


@pytest.mark.parametrize("fault_id", SIGNAL_FAULTS)
def test_a_signal_fault_follows_its_condition(fault_id: str) -> None:
    table = FaultTable()
    raised = table.set(fault_id, True, now=T0)
    assert raised is not None
    assert raised.active
    assert raised.since == T0_ISO
    assert table.active() == [raised]
    cleared = table.set(fault_id, False, now=T1)
    assert cleared is not None
    assert not cleared.active
    assert cleared.since is None
    assert table.active() == []


def test_a_signal_that_stays_as_it_was_changes_nothing() -> None:
    table = FaultTable()
    assert table.set("water_flow", False, now=T0) is None
    assert table.set("water_flow", True, value=0.4, now=T0) is not None
    assert table.set("water_flow", True, value=0.4, now=T1) is None


def test_an_active_fault_keeps_its_since_and_takes_a_new_value() -> None:
    table = FaultTable()
    table.set("water_temp", True, value=30.2, now=T0)
    updated = table.set("water_temp", True, value=31.0, now=T1)
    assert updated is not None
    assert updated.since == T0_ISO
    assert updated.value == 31.0


def test_a_fault_that_comes_back_has_a_new_since() -> None:
    table = FaultTable()
    table.set("lid_open", True, now=T0)
    table.set("lid_open", False, now=T0 + 1)
    again = table.set("lid_open", True, now=T1)
    assert again is not None
    assert again.since == T1_ISO


def test_a_cleared_fault_drops_its_value_and_detail() -> None:
    table = FaultTable()
    table.set("water_flow", True, value=0.2, message="ain1 below 1.5", now=T0)
    table.set("water_flow", False, now=T1)
    fault = table.get("water_flow")
    assert (fault.value, fault.message) == (None, RULES["water_flow"].text)


@pytest.mark.parametrize("fault_id", SOFTWARE_FAULTS + RESET_FAULTS)
def test_set_is_only_for_signal_faults(fault_id: str) -> None:
    with pytest.raises(ValueError, match="not a signal fault"):
        FaultTable().set(fault_id, True, now=T0)


@pytest.mark.parametrize("fault_id", SIGNAL_FAULTS)
def test_raise_is_only_for_software_faults(fault_id: str) -> None:
    with pytest.raises(ValueError, match="follows a signal"):
        FaultTable().raise_(fault_id, now=T0)


def test_the_daemon_naming_an_unknown_fault_is_a_bug() -> None:
    with pytest.raises(ValueError, match="unknown fault"):
        FaultTable().set("smoke", True, now=T0)
    with pytest.raises(ValueError, match="unknown fault"):
        FaultTable().raise_("smoke", now=T0)


# --- software faults


@pytest.mark.parametrize("fault_id", SOFTWARE_FAULTS + RESET_FAULTS)
def test_a_software_fault_is_raised(fault_id: str) -> None:
    table = FaultTable()
    fault = table.raise_(fault_id, now=T0)
    assert fault is not None
    assert fault.active
    assert fault.since == T0_ISO
    assert table.get(fault_id) == fault


def test_a_second_raise_keeps_since_and_updates_value_and_message() -> None:
    table = FaultTable()
    table.raise_("serial", value=10, message="frame error", now=T0)
    again = table.raise_("serial", value=12, message="data overrun", now=T1)
    assert again is not None
    assert again.since == T0_ISO
    assert again.value == 12
    assert again.message == "serial link error after 12 lines processed: data overrun"
    assert table.raise_("serial", value=12, message="data overrun", now=T1 + 5) is None


# --- clear


@pytest.mark.parametrize("fault_id", SOFTWARE_FAULTS)
def test_fault_clear_clears_serial_lexical_and_underflow(fault_id: str) -> None:
    table = FaultTable()
    table.raise_(fault_id, value=3, now=T0)
    fault = table.clear(fault_id)
    assert not fault.active
    assert fault.since is None
    assert fault.value is None
    assert table.get(fault_id) == fault


def test_clearing_an_inactive_clearable_fault_is_a_harmless_no_op() -> None:
    table = FaultTable()
    before = table.get("lexical")
    assert table.clear("lexical") == before


def test_estop_cannot_be_cleared_by_software() -> None:
    table = FaultTable()
    table.set("estop", True, now=T0)
    with pytest.raises(FaultError, match="estop clears only when the input is released") as err:
        table.clear("estop")
    assert err.value.code == -32602
    assert table.get("estop").active


@pytest.mark.parametrize("fault_id", ["lid_open", "lid_closed", "water_flow", "water_temp"])
def test_signal_faults_cannot_be_cleared_by_software(fault_id: str) -> None:
    table = FaultTable()
    table.set(fault_id, True, now=T0)
    with pytest.raises(FaultError, match=f"{fault_id} clears only when its condition goes away"):
        table.clear(fault_id)
    assert table.get(fault_id).active


@pytest.mark.parametrize("fault_id", RESET_FAULTS)
def test_syntax_and_internal_clear_only_with_machine_reset(fault_id: str) -> None:
    table = FaultTable()
    table.raise_(fault_id, now=T0)
    with pytest.raises(FaultError, match=rf"{fault_id} clears only with machine\.reset") as err:
        table.clear(fault_id)
    assert err.value.code == -32602
    assert err.value.message == f"{fault_id} clears only with machine.reset"
    assert table.get(fault_id).active


def test_a_refused_clear_is_refused_even_when_the_fault_is_not_active() -> None:
    with pytest.raises(FaultError, match=r"syntax clears only with machine\.reset"):
        FaultTable().clear("syntax")


@pytest.mark.parametrize(
    "ask",
    [
        lambda table: table.clear("smoke"),
        lambda table: table.override("smoke", True),
        lambda table: table.get("smoke"),
    ],
    ids=["clear", "override", "get"],
)
def test_an_unknown_fault_is_an_invalid_param(ask: Callable[[FaultTable], Fault]) -> None:
    with pytest.raises(FaultError, match="unknown fault 'smoke'") as err:
        ask(FaultTable())
    assert err.value.code == -32602


# --- override


@pytest.mark.parametrize("fault_id", OVERRIDABLE)
def test_an_override_does_not_change_active(fault_id: str) -> None:
    table = FaultTable()
    table.set(fault_id, True, now=T0)
    fault = table.override(fault_id, True)
    assert fault.overridden
    assert fault.active
    assert fault.since == T0_ISO
    fault = table.override(fault_id, False)
    assert not fault.overridden
    assert fault.active


@pytest.mark.parametrize("fault_id", NOT_OVERRIDABLE)
def test_faults_that_cannot_be_overridden_are_refused(fault_id: str) -> None:
    table = FaultTable()
    with pytest.raises(FaultError, match=f"^{fault_id} cannot be overridden$") as err:
        table.override(fault_id, True)
    assert err.value.code == -32602
    assert not table.get(fault_id).overridden


def test_an_override_is_kept_while_the_fault_comes_and_goes() -> None:
    table = FaultTable()
    table.override("lid_open", True)  # set before the lid opens
    table.set("lid_open", True, now=T0)
    assert table.get("lid_open").overridden
    table.set("lid_open", False, now=T1)
    assert table.get("lid_open").overridden
    assert table.indicator() == Indicator.NORMAL


# --- machine.reset


def test_reset_clears_every_software_fault_and_leaves_signal_faults() -> None:
    table = FaultTable()
    for fault_id in FAULT_IDS:
        make_active(table, fault_id)
    table.override("water_flow", True)
    changed = table.reset()
    assert sorted(f.id for f in changed) == sorted(SOFTWARE_FAULTS + RESET_FAULTS)
    assert all(not f.active for f in changed)
    assert [f.id for f in table.active()] == SIGNAL_FAULTS
    assert table.get("water_flow").overridden  # an operator's override survives a reset


def test_reset_reports_only_what_changed() -> None:
    table = FaultTable()
    table.raise_("syntax", now=T0)
    table.set("estop", True, now=T0)
    assert [f.id for f in table.reset()] == ["syntax"]
    assert table.reset() == []


# --- blocking and the indicator


def blocking_ids(table: FaultTable) -> list[str]:
    return [f.id for f in table.blocking()]


@pytest.mark.parametrize("fault_id", NOT_OVERRIDABLE)
def test_every_job_fault_blocks_and_alerts(fault_id: str) -> None:
    table = FaultTable()
    make_active(table, fault_id)
    assert blocking_ids(table) == [fault_id]
    assert table.indicator() == Indicator.ALERT


@pytest.mark.parametrize("fault_id", ["lid_open", "water_flow", "water_temp"])
def test_an_overridable_fault_blocks_until_it_is_overridden(fault_id: str) -> None:
    table = FaultTable()
    table.set(fault_id, True, now=T0)
    assert blocking_ids(table) == [fault_id]
    assert table.indicator() == Indicator.ALERT
    table.override(fault_id, True)
    assert blocking_ids(table) == []
    assert table.indicator() == Indicator.WARNING


def test_an_overridden_water_flow_alone_warns_and_does_not_block() -> None:
    table = FaultTable()
    table.override("water_flow", True)
    table.set("water_flow", True, value=0.3, now=T0)
    assert table.indicator() == Indicator.WARNING
    assert table.blocking() == []


def test_lid_closed_alone_alerts_but_does_not_block() -> None:
    table = FaultTable()
    table.set("lid_closed", True, now=T0)
    assert table.get("lid_closed").severity == Severity.RECOVERABLE
    assert table.indicator() == Indicator.ALERT
    assert table.blocking() == []


def test_serial_alerts_and_blocks() -> None:
    table = FaultTable()
    table.raise_("serial", value=7, now=T0)
    assert table.indicator() == Indicator.ALERT
    assert blocking_ids(table) == ["serial"]


def test_alert_wins_over_warning() -> None:
    table = FaultTable()
    table.set("water_temp", True, now=T0)
    table.override("water_temp", True)
    table.set("lid_closed", True, now=T0)
    assert table.indicator() == Indicator.ALERT
    table.override("lid_closed", True)
    assert table.indicator() == Indicator.WARNING
    table.set("water_temp", False, now=T1)
    table.set("lid_closed", False, now=T1)
    assert table.indicator() == Indicator.NORMAL


def test_an_override_on_an_inactive_fault_shows_nothing() -> None:
    table = FaultTable()
    for fault_id in OVERRIDABLE:
        table.override(fault_id, True)
    assert table.indicator() == Indicator.NORMAL
    assert table.active() == []


def test_blocking_faults_are_listed_in_table_order() -> None:
    table = FaultTable()
    table.raise_("underflow", now=T0)
    table.set("water_flow", True, now=T0)
    table.set("estop", True, now=T0)
    table.set("lid_closed", True, now=T0)
    assert blocking_ids(table) == ["estop", "water_flow", "underflow"]
    assert [f.id for f in table.active()] == ["estop", "lid_closed", "water_flow", "underflow"]


def test_a_cleared_fault_no_longer_blocks() -> None:
    table = FaultTable()
    table.raise_("underflow", now=T0)
    table.clear("underflow")
    assert table.blocking() == []
    assert table.indicator() == Indicator.NORMAL
