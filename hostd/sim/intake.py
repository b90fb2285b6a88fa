"""The simulated g2core's intake: which data line is read next, and which are dropped.

The layer of `Board` (board.py) above its output (output.py). Data lines are
read in order, and only when the planner has room, so line-mode flow control
is real [7.1]; none is read while a probing cycle runs or (from 101.02) a
hold is in place. A `%` or ^D then drops the lines that came in before it on
its own port (xio.cpp `xio_flush_to_command`), and a queue flush on 101.05+
every data port's. commands.py asks here whether to read a line and
marks the controls it reads; stops.py flushes; a reset (board.py) and a
NUL (controller.py) drop what is queued.
"""

from __future__ import annotations

from hostd.sim.gcode import Probe
from hostd.sim.output import Hold, Output


class Intake(Output):
    """The receive queues' side of the planner: what is read next, what is dropped."""

    # --- data lines: read in order, only when the planner has room [7.1]

    def _dispatchable(self) -> bool:
        if self._ack is not None or self.output_blocked:
            return False
        if self._probing is not None or any(isinstance(b, Probe) for b in self.planner):
            return False  # cm_probing_cycle_callback: nothing is read until the cycle ends
        if self.hold != Hold.OFF and not self.build.kill_alarms:
            return False  # cm_feedhold_command_blocker (101.03 cycle_feedhold.cpp:294)
        if not self.state.is_lockout and len(self.planner) >= self.config.planner_depth:
            return False  # in a lockout lines are drained and rejected regardless [10]
        return any(self.rx.values()) or any(self.rx_controls.values())

    def discard_rx(self, port: str | None = None, *, controls: bool = True) -> None:
        """Drop data lines not yet read: they never get a response [7.1]. A flush to the
        command (`controls=False`) keeps the controls that came after it."""
        for name in [port] if port is not None else list(self.rx):
            if name in self.rx:
                self._rx_out[name] += len(self.rx[name])
                self.rx[name].clear()
                self._rx_bytes[name] = 0
            if controls and name in self.rx_controls:
                self.rx_controls[name].clear()

    def _control_read(self, port: str, mark: int | None) -> None:
        """`readline` returned a control from `port`: a flush to the command now drops the
        data lines that came in before it (`mark`; None: every one queued so far)."""
        if port in self._control_last:
            self._control_last[port] = True
            self._flush_mark[port] = self._rx_in[port] if mark is None else mark

    def _flush_to_command(self) -> None:
        """`xio_flush_to_command`: every port whose last line read was a control drops the
        data lines that came in before that control (xio.cpp:984-1017, `flushToCommand`:
        the read pointer moves to where the scan stopped, just past the control, :1004);
        the lines behind it, and the other ports' lines, stay.

        On a two-port link a ^D on the control port flushes that port alone: the
        data port's lines are read and run after it, up to the data port's own ^D.
        """
        for port, last in self._control_last.items():
            if not last:
                continue
            self._control_last[port] = False
            queue, mark = self.rx[port], self._flush_mark[port]
            while queue and self._rx_out[port] < mark:
                self._rx_bytes[port] -= queue.popleft().size
                self._rx_out[port] += 1
