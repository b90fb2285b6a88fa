"""The simulated g2core's commands: data lines, JSON and text commands, G-code.

The layer of `Board` (board.py) above its planner (planner.py): a data line
read from RX is told apart by its first character and run. JSON (`{...}`)
and text (`$...`) commands are GETs and SETs of settings and of the board's
functions (`clear`, `alarm`, `defa`, `sr`, ...), answered in JSON [7.1, 11];
G-code goes through the interpreter into the planner, or into the secondary
planner in a hold [8], with soft limits checked on the way [10].
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from hostd.protocol.states import MachineState
from hostd.protocol.status import Status
from hostd.sim import gcode, relaxed, reports
from hostd.sim.config import AXES, EPS
from hostd.sim.gcode import Dwell, Home, Move, SetPosition
from hostd.sim.output import Hold
from hostd.sim.planner import Planner
from hostd.sim.scanner import Realtime
from hostd.sim.settings import Settings

RX_REPORT = 254  # `{rx:n}` is a constant on ARM [7.1]


class Commands(Planner):
    """Data lines and control lines, read and run: what every line does."""

    # --- data lines: read in order, only when the planner has room [7.1]

    def _dispatch(self) -> bool:
        if not self._dispatchable():
            return False
        for port, controls in self.rx_controls.items():
            if controls:  # readline returns a port's controls ahead of its data lines
                event, mark = controls.popleft()
                if isinstance(event, Realtime):
                    self.realtime(port, event.char, mark)
                else:
                    self._control_line(event.text, event.linelen, port, mark)
                return True
        for port, queue in self.rx.items():
            if queue:
                line = queue.popleft()
                self._rx_bytes[port] -= line.size
                self._rx_out[port] += 1
                self._control_last[port] = False
                self._data_line(line.text.decode("latin-1"))
                return True
        return False

    def _control_line(self, text: bytes, linelen: int, port: str, mark: int | None = None) -> None:
        """A `{...}` line read as a control: run at once, and its port's last read a control.
        `mark`: the port's data lines that came in before it (None: all there are)."""
        self._control_read(port, mark)
        self._json(text.decode("latin-1"), linelen, data=False)
        self._flush_sr()

    def _data_line(self, text: str) -> None:
        linelen = len(text)
        stripped = text.lstrip(" \t")
        first = stripped[:1]
        if first == "%":
            return  # swallowed by the single-character branch, no response [2.2]
        if first and first in "!~\x04\x05\x18":
            self.realtime("", ord(first))
            return
        if first == "{":
            self._json(stripped, linelen, data=True)
        elif first == "?":
            self._respond({"sr": self._sr_full()}, Status.OK, linelen, data=True)
        elif first == "$":
            self._text(stripped, linelen)
        else:
            refused, self.refuse_next = self.refuse_next, None
            status, n = self._gcode(text) if refused is None else (Status(refused), 0)
            body: dict[str, Any] = {"gc": text} if self._jv >= 5 else {}
            self._respond(body, status, linelen, data=True, n=n)
            self._sr_requested = True

    # --- JSON and text commands

    def _json(self, text: str, linelen: int, *, data: bool) -> None:
        try:
            pairs = relaxed.parse(text)
        except relaxed.RelaxedJsonError:
            body: dict[str, Any] = {"err": text} if self._jv >= 2 else {}
            self._respond(body, Status.JSON_SYNTAX_ERROR, linelen, data=data)
            return
        body = {}
        status, n = Status.OK, 0
        for key, value in pairs.items():
            status, line = self._pair(key, value, body)
            n = n or line
            if status != Status.OK:
                break
        self._respond(body, status, linelen, data=data, n=n)
        self._sr_requested = True

    def _text(self, text: str, linelen: int) -> None:
        """`$key`, `$key=value`, `$clear`: text-mode commands, answered in JSON [11]."""
        command = relaxed.normalize(text[1:])
        body: dict[str, Any] = {}
        if command in ("", "$"):
            body["sys"] = self.settings.system_group()
            self._respond(body, Status.OK, linelen, data=True)
            return
        key, eq, raw = command.partition("=")
        value = _text_value(raw) if eq else None
        status, n = self._pair(key, value, body)
        self._respond(body, status, linelen, data=True, n=n)
        self._sr_requested = True

    def _pair(self, key: str, value: relaxed.Value, body: dict[str, Any]) -> tuple[Status, int]:
        """One name/value pair: a GET (value None) or a SET; returns status and N word."""
        if value is None:
            return self._get(key, body), 0
        if isinstance(value, str) and gcode.is_program_end(value):
            self._parse_clear()
        rejected = self._rejection()
        if rejected is not None:  # SETs are actions: drained and rejected [10]
            body[key] = _echo(value)
            return rejected, 0
        if key == "gc2" and not self.build.in_hold_gcode:
            return Status.UNRECOGNIZED_NAME, 0  # no `gc2` before 101.02 (config_app.cpp)
        if key in ("gc", "gc2"):
            if not isinstance(value, str):
                body[key] = _echo(value)
                return Status.VALUE_TYPE_ERROR, 0
            if self._jv >= 5:
                body[key] = value
            return self._gcode(value, in_hold=key == "gc2")
        if key == "sr":
            return self._set_sr(value, body), 0
        return self._set(key, value, body), 0

    def _get(self, key: str, body: dict[str, Any]) -> Status:
        body[key] = None
        if key == "sr":
            body[key] = self._sr_full()
        elif key in ("clear", "clr"):
            self._clear()
        elif key == "alarm":
            self._lockout(MachineState.ALARM, Status.ALARM, "sent by host")
        elif key == "shutd":
            self._lockout(MachineState.SHUTDOWN, Status.SHUTDOWN, "sent by host", unhome=True)
        elif key == "panic":
            self._lockout(MachineState.PANIC, Status.PANIC, "sent by host")
        elif key == "er":
            self._exception(Status.GENERIC_EXCEPTION_REPORT, "bogus exception report")
        elif key == "sys":
            body[key] = self.settings.system_group()
        elif key == "qr":
            body[key] = self._free
        elif key in ("qi", "qo"):
            body[key] = self._qi if key == "qi" else self._qo
            setattr(self, f"_{key}", 0)
        elif key == "rx":
            body[key] = RX_REPORT
        elif key in _COORD_GROUPS or key == "g92":
            # config_app.cpp's `g54`.. groups and `g92`: per axis, in the units in force
            # (F_CONVERT).
            scale = self.interp.scale
            values = (
                self.interp.offsets
                if key == "g92"
                else self.interp.coords[_COORD_GROUPS.index(key)]
            )
            body[key] = {a: reports.number(values[a] / scale, 3) for a in AXES}
        elif key in self.settings:
            body[key] = self.settings.get(key)
        elif key in self.unexposed:
            body[key] = None  # gpio.h: a reader with no pin answers TYPE_NULL
        elif key in self.settings.report_keys:
            body[key] = self._values(self._clock())[key]
            if key == f"in{int(self.settings['prbin'])}" and self.touch_reads:
                self.touch_reads -= 1  # the operator saw it read and lets go
        else:
            return Status.UNRECOGNIZED_NAME
        return Status.OK

    def _set(self, key: str, value: relaxed.Value, body: dict[str, Any]) -> Status:
        body[key] = _echo(value)
        if key in ("clear", "clr", "alarm", "shutd", "panic"):
            return self._get(key, body)  # functions run the same either way
        if key in self.settings.report_keys:
            # The spindle's `spd` (100.26) and `spc` (101.03) have setters on the board;
            # hostd never writes them, and this board keeps them read-only.
            return Status.PARAMETER_IS_READ_ONLY
        if key == "defa":
            return self._defaults(value, body)
        if key not in self.settings:
            return Status.UNRECOGNIZED_NAME
        status = self.settings.set(key, value)
        if status == Status.OK:
            body[key] = self.settings.get(key)
        return status

    def _defaults(self, value: relaxed.Value, body: dict[str, Any]) -> Status:
        """config.cpp `set_defaults`: every setting back to the profile's default.

        `_set_defa` prints its startup message ("Initializing configs...", status
        15) before the line's answer, and the answer is `{"defa":true}` [11].
        """
        if not value:
            return Status.OK  # help_defa: a help screen (text), which hostd never asks for
        self.settings = Settings(self.config)
        self._sr_last = {}
        self._init_message_due = True
        body["defa"] = True
        return Status.OK

    def _set_sr(self, value: relaxed.Value, body: dict[str, Any]) -> Status:
        """`{sr:{...}}` replaces the report list; the answer is a full report [4]."""
        body["sr"] = _echo(value)
        status = self.settings.set_status_report(value)
        if status == Status.OK:
            self._sr_last = {}
            body["sr"] = self._sr_full()
        return status

    # --- G-code

    def _gcode(self, text: str, *, in_hold: bool = False) -> tuple[Status, int]:
        if gcode.is_program_end(text):
            self._parse_clear()
        rejected = self._rejection()
        if rejected is not None:
            return rejected, 0
        if in_hold and self.hold == Hold.HOLD:
            return self._gcode_in_hold(text)
        outcome = self.interp.execute(text, self._soft_limits)
        self._soft_limit_alarm(outcome.status)
        if outcome.alarm:  # cm_straight_probe refused it with cm_alarm()
            self._lockout(MachineState.ALARM, outcome.status, outcome.alarm)
        for block in outcome.blocks:
            self.planner.append(block)
            self._qi += 1
            self._last_block_at = self._clock()
            if isinstance(block, Move | Dwell) and self._at_rest_for_a_cycle():
                self._set_state(MachineState.RUN)  # cm_cycle_start, as the move is parsed
        return outcome.status, outcome.n

    def _gcode_in_hold(self, text: str) -> tuple[Status, int]:
        """`{gc2:...}` in a hold: the secondary planner runs it at once [8, seed 002]."""
        if self._p2 is None:
            self._p2 = self.interp.copy()
            self._p2.sync(self.position)
        outcome = self._p2.execute(text, self._soft_limits)
        self._soft_limit_alarm(outcome.status)
        for block in outcome.blocks:
            if isinstance(block, Move):
                self.position = dict(block.target)
            elif isinstance(block, Home):
                for axis in block.axes:
                    self.position[axis] = 0.0
                    self.homed[axis] = True
            elif isinstance(block, SetPosition):
                self.position.update(block.values)
                for axis in block.values:
                    self.homed[axis] = True
            self._sr_requested = True
        return outcome.status, outcome.n

    def _soft_limits(self, target: Mapping[str, float]) -> Status:
        """Soft limits apply to homed axes while `sl` is on [10, seed 000]."""
        if not self.settings["sl"]:
            return Status.OK
        for i, axis in enumerate(AXES):
            if not self.homed[axis]:
                continue
            if target[axis] < self.settings[f"{axis}tn"] - EPS:
                return Status(Status.SOFT_LIMIT_EXCEEDED_XMIN + 2 * i)
            if target[axis] > self.settings[f"{axis}tm"] + EPS:
                return Status(Status.SOFT_LIMIT_EXCEEDED_XMAX + 2 * i)
        return Status.OK

    def _soft_limit_alarm(self, status: Status) -> None:
        if Status.SOFT_LIMIT_EXCEEDED <= status <= Status.SOFT_LIMIT_EXCEEDED_ARC:
            self._lockout(MachineState.ALARM, status, "soft_limits")


_COORD_GROUPS = ("g54", "g55", "g56", "g57", "g58", "g59")


def _echo(value: relaxed.Value) -> Any:
    if isinstance(value, float):
        return reports.number(value, 5)
    if isinstance(value, dict):
        return {k: _echo(v) for k, v in value.items()}
    return value


def _text_value(raw: str) -> relaxed.Value:
    """The value of `$key=value`: a number, t/f, or the text itself."""
    if not raw or raw.startswith("n"):
        return None
    try:
        return float(raw)
    except ValueError:
        pass
    if raw in ("t", "true", "f", "false"):
        return raw.startswith("t")
    return raw
