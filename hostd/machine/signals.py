"""Where a machine's physical signals come from, and which faults they make.

Lid switch, laser selection, coolant flow and temperature reach the daemon
as keys of the controller's status reports (digital inputs `in1`..,
analogue inputs, or any key the board reports). Which key means what is
per-machine configuration, `[machines.signals]`: each signal names a key and
one condition on its value. A machine that configures no signals never
raises those faults. The controller's SHUTDOWN state is always an e-stop
source; `estop` here only adds another.

A single-laser cutter with a lid switch and a coolant flow switch::

    [[machines]]
    id = "laser1"
    data_port = "/dev/serial/by-id/usb-Synthetos_TinyG_v2_0123-if00"

    [machines.signals]
    lid_open = { key = "in4", equals = 1 }
    main_laser = { key = "in5", equals = 1 }
    coolant_flow_low = { key = "in6", equals = 0 }  # the flow switch opens when flow stops

A cutter with a visible (alignment) laser, an analogue flow meter and a
coolant temperature probe; the temperature fault clears only once it is a
degree below its limit, so a reading that hovers at the limit does not
flap::

    [[machines]]
    id = "laser2"
    data_port = "/dev/serial/by-id/usb-Synthetos_TinyG_v2_4567-if00"

    [machines.signals]
    lid_open = { key = "in4", equals = true }
    main_laser = { key = "in5", equals = 1 }
    visible_laser = { key = "in7", equals = 1 }
    estop = { key = "in8", equals = 0 }

    [machines.signals.coolant_flow_low]
    key = "ain1"
    below = 1.5  # litres per minute

    [machines.signals.coolant_temp_high]
    key = "ain2"
    above = 28.0  # degrees C
    hysteresis = 1.0

A status report carries only the keys that changed, so the caller keeps the
last value of every key in `keys()` and passes them all to `evaluate`; a key
the board has never reported counts as inactive (unknown is not a fault).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, StrictBool, model_validator

Number = Annotated[float, Field(strict=True, allow_inf_nan=False)]

# The signals, in the order keys() lists them.
SIGNALS: tuple[str, ...] = (
    "estop",
    "lid_open",
    "main_laser",
    "visible_laser",
    "coolant_flow_low",
    "coolant_temp_high",
)


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Source(_Strict):
    """A status report key and the one condition under which the signal is active."""

    key: Annotated[str, Field(pattern=r"^[a-z][a-z0-9_]{0,7}$")]
    equals: StrictBool | Number | None = None  # true equals 1, false equals 0
    above: Number | None = None
    below: Number | None = None
    # Only with above/below: once active, the signal stays active until the
    # value is this far back on the safe side of the threshold.
    hysteresis: Annotated[float, Field(strict=True, ge=0, allow_inf_nan=False)] = 0.0

    @model_validator(mode="after")
    def _one_condition(self) -> Source:
        given = [name for name in ("equals", "above", "below") if getattr(self, name) is not None]
        if len(given) != 1:
            got = " and ".join(given) if given else "none"
            raise ValueError(f"give exactly one condition of equals, above, below (got {got})")
        if self.hysteresis and self.equals is not None:
            raise ValueError("hysteresis goes with above or below, not with equals")
        return self

    def active(self, value: Any, was_active: bool) -> bool:
        """Whether `value` (None: never reported) makes the signal active."""
        if isinstance(value, bool):
            value = int(value)
        if not isinstance(value, int | float):
            return False  # unknown, or not a number: not a fault
        if self.equals is not None:
            return value == self.equals
        margin = self.hysteresis if was_active else 0.0
        if self.above is not None:
            return value > self.above - margin
        assert self.below is not None
        return value < self.below + margin


class SignalsConfig(_Strict):
    """`[machines.signals]`: every signal optional."""

    estop: Source | None = None
    lid_open: Source | None = None
    main_laser: Source | None = None
    visible_laser: Source | None = None
    coolant_flow_low: Source | None = None
    coolant_temp_high: Source | None = None

    @model_validator(mode="after")
    def _lid_and_lasers_together(self) -> SignalsConfig:
        lasers = self.main_laser is not None or self.visible_laser is not None
        if self.lid_open is not None and not lasers:
            raise ValueError(
                "lid_open needs main_laser (for the lid_open fault) and/or visible_laser "
                "(for the lid_closed fault): a lid fault depends on which laser is selected"
            )
        if lasers and self.lid_open is None:
            raise ValueError("main_laser and visible_laser are used only with lid_open")
        return self

    def sources(self) -> dict[str, Source]:
        """The configured signals, by name."""
        found = {name: getattr(self, name) for name in SIGNALS}
        return {name: source for name, source in found.items() if source is not None}

    def keys(self) -> list[str]:
        """The status report keys the board must report, each once."""
        return list(dict.fromkeys(source.key for source in self.sources().values()))

    def evaluate(self, values: Mapping[str, Any], previous: Mapping[str, bool]) -> dict[str, bool]:
        """Which configured signals are active, from the last known value of every key.

        `previous` is the last result (for hysteresis); `{}` at first.
        """
        return {
            name: source.active(values.get(source.key), previous.get(name, False))
            for name, source in self.sources().items()
        }


# The faults whose value is a reading (behaviour.md: every fault has a value), by the
# signal whose key gives it: the coolant's flow and temperature as the board reports them.
READINGS: dict[str, str] = {"water_flow": "coolant_flow_low", "water_temp": "coolant_temp_high"}


def fault_readings(config: SignalsConfig, values: Mapping[str, Any]) -> dict[str, float]:
    """Each reading fault's reading now: the last number of its signal's key, where the
    signal is a measure against a threshold (`above`, `below`); a switch (`equals`)
    reads 0 or 1, which says nothing the fault's name does not."""
    sources = config.sources()
    readings: dict[str, float] = {}
    for fault, signal in READINGS.items():
        source = sources.get(signal)
        if source is None or source.equals is not None:
            continue
        reading = values.get(source.key)
        if isinstance(reading, int | float) and not isinstance(reading, bool):
            readings[fault] = reading
    return readings


def fault_conditions(signals: Mapping[str, bool]) -> dict[str, bool]:
    """The faults the signals decide (behaviour.md "Faults"), only those configured."""
    faults: dict[str, bool] = {}
    if "estop" in signals:
        faults["estop"] = signals["estop"]
    if "lid_open" in signals and "main_laser" in signals:
        faults["lid_open"] = signals["lid_open"] and signals["main_laser"]
    if "lid_open" in signals and "visible_laser" in signals:
        faults["lid_closed"] = not signals["lid_open"] and signals["visible_laser"]
    if "coolant_flow_low" in signals:
        faults["water_flow"] = signals["coolant_flow_low"]
    if "coolant_temp_high" in signals:
        faults["water_temp"] = signals["coolant_temp_high"]
    return faults
