"""Where g2core raises its alarms, shutdowns and panics: one row per call in the firmware.

Each row is one call of `cm_alarm`, `cm_shutdown` or `cm_panic` in synthetos/g2
`g2core/` (edge-preview, commit 1fb59404, fb 101.x), with the status and the
detail text that call passes and the file and line it is in.
`SimController.firmware_exception(site)` makes the simulated board do what
that call does (`alarm.cpp`): an exception report `{"er":{...}}` with that
status and detail, the lockout, and (but for a panic) a status report.
Tests walk this list, so every code the firmware raises that way goes through
the real path.

Calls whose detail is built at run time (`input %d`) are listed with a
plausible value. Status 141 (`STAT_ACTIVE_PLANE_IS_INVALID`) has no call
site in this source; hostd classifies it beside 140 all the same
(`hostd/protocol/status.py`), and a test may raise it with a `CallSite`
of its own.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from hostd.protocol.status import Status

Path = Literal["alarm", "shutdown", "panic"]


@dataclass(frozen=True, slots=True)
class CallSite:
    status: int
    path: Path  # which of cm_alarm / cm_shutdown / cm_panic is called
    detail: str  # the `msg` argument, printed after the status message
    where: str  # file:line in g2core/


def _site(status: int, path: Path, detail: str, where: str) -> CallSite:
    return CallSite(int(status), path, detail, where)


S = Status

CALL_SITES: tuple[CallSite, ...] = (
    # cm_alarm (alarm.cpp): a feedhold that ends in ALARM, an `er`, a status report.
    _site(S.ALARM, "alarm", "sent by host", "alarm.cpp:53"),
    _site(S.ALARM, "alarm", "input 4", "canonical_machine.cpp:184"),
    _site(S.LIMIT_SWITCH_HIT, "alarm", "input 1", "controller.cpp:518"),
    *(
        _site(code, "alarm", "soft_limits", "canonical_machine.cpp:879")
        for code in range(S.SOFT_LIMIT_EXCEEDED_XMIN, S.SOFT_LIMIT_EXCEEDED_CMAX + 1)
    ),
    _site(S.SOFT_LIMIT_EXCEEDED, "alarm", "arc soft_limits", "plan_arc.cpp:250"),
    _site(
        S.PROBE_CYCLE_FAILED,
        "alarm",
        "Already probing - cannot start another probe",
        "cycle_probing.cpp:203",
    ),
    _site(S.FEEDRATE_NOT_SPECIFIED, "alarm", "Feedrate is zero", "cycle_probing.cpp:208"),
    _site(S.AXIS_IS_MISSING, "alarm", "Axis is missing", "cycle_probing.cpp:214"),
    _site(
        S.NO_PROBE_INPUT_CONFIGURED, "alarm", "Probe input not configured", "cycle_probing.cpp:219"
    ),
    _site(S.PROBE_TRAVEL_TOO_SMALL, "alarm", "probe error", "cycle_probing.cpp:411"),
    _site(S.PROBE_IS_ALREADY_TRIPPED, "alarm", "probe error", "cycle_probing.cpp:411"),
    _site(S.PROBE_CYCLE_FAILED, "alarm", "probing failed", "cycle_probing.cpp:423"),
    _site(
        S.ARC_OFFSETS_MISSING_FOR_SELECTED_PLANE,
        "alarm",
        "arc offsets missing or zero",
        "plan_arc.cpp:238",
    ),
    _site(
        S.TEMPERATURE_CONTROL_ERROR, "alarm", "Sensor read failed 10 times.", "temperature.cpp:460"
    ),
    _site(
        S.TEMPERATURE_CONTROL_ERROR,
        "alarm",
        "Heater set, but sensor read failed.",
        "temperature.cpp:677",
    ),
    _site(
        S.ENCODER_ASSERTION_FAILURE,
        "alarm",
        "encoder stopped returning values",
        "kinematics_four_cable.h:684",
    ),
    # cm_shutdown: like an alarm, but the machine is no longer homed.
    _site(S.SHUTDOWN, "shutdown", "sent by host", "alarm.cpp:59"),
    _site(S.SHUTDOWN, "shutdown", "input 7", "safety_manager.h:138"),
    # cm_panic: motion halted, an `er`, and no status report requested.
    _site(S.PANIC, "panic", "sent by host", "alarm.cpp:65"),
    _site(S.PANIC, "panic", "input 9", "canonical_machine.cpp:204"),
    _site(
        S.BUFFER_FULL_FATAL,
        "panic",
        "_populate_unfiltered_status_report() sr link NULL",
        "report.cpp:411",
    ),
    _site(S.INTERNAL_ERROR, "panic", "mp_exec_move()", "plan_exec.cpp:305"),
    _site(S.INTERNAL_ERROR, "panic", "exec_aline()", "plan_exec.cpp:504"),
    _site(S.INTERNAL_ERROR, "panic", "st_prep_line() prep sync error", "stepper.cpp:674"),
    _site(S.PREP_LINE_MOVE_TIME_IS_INFINITE, "panic", "st_prep_line()", "stepper.cpp:676"),
    _site(S.PREP_LINE_MOVE_TIME_IS_NAN, "panic", "st_prep_line()", "stepper.cpp:678"),
    _site(S.FAILED_GET_PLANNER_BUFFER, "panic", "aline()", "plan_line.cpp:219"),
    _site(S.FAILED_GET_PLANNER_BUFFER, "panic", "mp_queue_command()", "planner.cpp:365"),
    _site(S.FAILED_GET_PLANNER_BUFFER, "panic", "mp_json_wait()", "planner.cpp:456"),
    _site(S.FAILED_GET_PLANNER_BUFFER, "panic", "mp_dwell()", "planner.cpp:478"),
    _site(S.ACTIVE_PLANE_IS_MISSING, "panic", "cm_arc_feed() impossible value", "plan_arc.cpp:160"),
    _site(
        S.STATE_MANAGEMENT_ASSERTION_FAILURE,
        "panic",
        "cm_get_combined_state() undefined state",
        "canonical_machine.cpp:413",
    ),
    _site(S.CONFIG_ASSERTION_FAILURE, "panic", "config_test_assertions()", "config.cpp:212"),
    _site(S.XIO_ASSERTION_FAILURE, "panic", "xio_test_assertions()", "xio.cpp:1365"),
    _site(S.ENCODER_ASSERTION_FAILURE, "panic", "encoder_test_assertions()", "encoder.cpp:64"),
    _site(S.STEPPER_ASSERTION_FAILURE, "panic", "stepper_test_assertions()", "stepper.cpp:209"),
    _site(S.PLANNER_ASSERTION_FAILURE, "panic", "planner_assert()", "planner.cpp:214"),
    _site(S.PLANNER_ASSERTION_FAILURE, "panic", "planner buffer is corrupted", "planner.cpp:218"),
    _site(
        S.CANONICAL_MACHINE_ASSERTION_FAILURE,
        "panic",
        "canonical_machine_test_assertions()",
        "canonical_machine.cpp:341",
    ),
    _site(
        S.CONTROLLER_ASSERTION_FAILURE,
        "panic",
        "controller_test_assertions()",
        "controller.cpp:538",
    ),
)
