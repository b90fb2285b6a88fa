"""machine.*: the machines, their lines, realtime commands and operations.

Every handler calls the Machine (hostd/machine/machine.py) or an operation of
hostd/machine/operations.py or probing.py; none reaches past it to the engine.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import Field, field_validator, model_validator

from hostd.api.methods.base import refused
from hostd.api.methods.params import Distance, Feed, JobFile, MachineParams
from hostd.api.rpc import Methods, RpcError
from hostd.machine import operations, probing
from hostd.machine.guard import check_jog, check_send, send_maintenance
from hostd.protocol.commands import Realtime
from hostd.protocol.gcode import JOG_AXES

if TYPE_CHECKING:
    from hostd.api.methods.base import Api

AXES = JOG_AXES
HomeAxis = Literal["x", "y", "z", "a", "b", "c"]
Speed = Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0, le=1_000_000)]
Percent = Annotated[int, Field(strict=True, ge=1, le=1000)]


class OverrideParams(MachineParams):
    """Percentages; each optional, at least one."""

    feed: Percent | None = None
    rapid: Percent | None = None
    spindle: Percent | None = None

    @model_validator(mode="after")
    def _something(self) -> OverrideParams:
        if self.feed is None and self.rapid is None and self.spindle is None:
            raise ValueError("give feed, rapid or spindle")
        return self


class HomeParams(MachineParams):
    """`axes`: which to home (absent: all); each once."""

    axes: Annotated[list[HomeAxis], Field(min_length=1, max_length=6)] | None = None

    @field_validator("axes")
    @classmethod
    def _once(cls, axes: list[str] | None) -> list[str] | None:
        if axes is not None and len(set(axes)) != len(axes):
            raise ValueError("each axis once")
        return axes


class ZeroParams(MachineParams):
    """`axes`: the work position each named axis should read now."""

    axes: Annotated[dict[HomeAxis, Distance], Field(min_length=1)]


class SpindleParams(MachineParams):
    state: Literal["cw", "ccw", "off"]
    speed: Speed | None = None


Length = Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0, le=100)]
Travel = Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0, le=500)]
ProbeFeed = Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0, le=5000)]
Seconds = Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0, le=120)]


class ProbeParams(MachineParams):
    """A touch-plate probe; each length in mm, the feed in mm/min. Absent: the
    machine's `[machines.probe]` value. `tool_diameter` places X and Y for "xyz" (the
    bit's side meets the plate's walls); `confirmed` stands in for seeing the probe
    input only where the board cannot show it; `wait` is how long the operator has
    to touch the plate to the bit (hostd/machine/probing.py)."""

    kind: Literal["z", "xyz"]
    plate: Length | None = None
    feed: ProbeFeed | None = None
    max_travel: Travel | None = None
    retract: Length | None = None
    tool_diameter: Length | None = None
    confirmed: Annotated[bool, Field(strict=True)] = False
    wait: Seconds = 30.0


PowerPercent = Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0, le=100)]


class LaserTestParams(MachineParams):
    """`power`: percent of full power (above 0, at most the config's laser_test_max);
    `duration_s`: at most 2."""

    power: Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0, le=100)]
    duration_s: Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0, le=2)]


class FrameParams(MachineParams):
    """`file`: a file of the jobs directory; `power` percent (0: beam off); `feed` mm/min."""

    file: JobFile
    power: PowerPercent = 0
    feed: Feed | None = None


class SendParams(MachineParams):
    line: str
    timeout: Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0, le=3600)] = 10.0


class JogParams(MachineParams):
    """Distances in the machine's units, |d| <= MAX_DISTANCE; MIN_FEED <= feed <= MAX_FEED."""

    axes: dict[str, Distance]
    feed: Feed

    @field_validator("axes")
    @classmethod
    def _known_axes(cls, axes: dict[str, float]) -> dict[str, float]:
        if not axes:
            raise ValueError("at least one axis")
        unknown = sorted(set(axes) - set(AXES))
        if unknown:
            raise ValueError(f"unknown axes {unknown}: use {', '.join(AXES)}")
        return axes


class MachineMethods:
    def __init__(self, api: Api) -> None:
        self.api = api

    async def machine_list(self) -> list[dict[str, Any]]:
        out = []
        for machine in self.api.daemon.machines.values():
            snap = machine.snapshot()
            out.append(
                {
                    "id": machine.id,
                    "dialect": machine.config.dialect,
                    "supervisor": snap["supervisor"],
                    "state": snap["state"],
                }
            )
        return out

    async def machine_status(self, p: MachineParams) -> dict[str, Any]:
        return self.api.machine(p.machine).snapshot()

    async def machine_connect(self, p: MachineParams) -> dict[str, Any]:
        machine = self.api.machine(p.machine)
        await machine.connect()
        return machine.snapshot()

    async def machine_disconnect(self, p: MachineParams) -> dict[str, Any]:
        machine = self.api.machine(p.machine)
        await machine.disconnect()
        return machine.snapshot()

    async def machine_send(self, p: SendParams) -> dict[str, Any]:
        machine = self.api.machine(p.machine)

        with refused():
            await operations.modes_known(machine)  # an absurd `$J=` is judged in the units in force
            check_send(machine, p.line)  # maintenance commands: machine.maintenance only
            response = await machine.send(p.line, timeout=p.timeout)
        return {"status": response.status, "r": response.body}

    async def machine_maintenance(self, p: SendParams) -> dict[str, Any]:
        """One maintenance command, on purpose, where the machine's config allows it."""
        machine = self.api.machine(p.machine)
        with refused():
            response = await send_maintenance(machine, p.line, p.timeout)
        return {"status": response.status, "r": response.body}

    async def machine_feedhold(self, p: MachineParams) -> dict[str, Any]:
        self.api.machine(p.machine).feedhold()
        return {}

    async def machine_cycle_start(self, p: MachineParams) -> dict[str, Any]:
        self.api.machine(p.machine).cycle_start()
        return {}

    async def machine_queue_flush(self, p: MachineParams) -> dict[str, Any]:
        self.api.machine(p.machine).realtime(Realtime.QUEUE_FLUSH)
        return {}

    async def machine_job_kill(self, p: MachineParams) -> dict[str, Any]:
        self.api.machine(p.machine).realtime(Realtime.JOB_KILL)
        return {}

    async def machine_reset(self, p: MachineParams) -> dict[str, Any]:
        await self.api.machine(p.machine).reset()
        return {}

    async def machine_clear(self, p: MachineParams) -> dict[str, Any]:
        await self.api.machine(p.machine).clear()
        return {}

    async def machine_alarm(self, p: MachineParams) -> dict[str, Any]:
        await self.api.machine(p.machine).alarm()  # refused where the dialect has none
        return {}

    async def machine_shutdown(self, p: MachineParams) -> dict[str, Any]:
        await self.api.machine(p.machine).shutdown()
        return {}

    async def machine_jog(self, p: JogParams) -> dict[str, Any]:
        machine = self.api.machine(p.machine)

        with refused():
            await operations.modes_known(machine)  # its bound is checked in the units in force
            check_jog(machine, p.axes)
        job = await machine.jog(p.axes, p.feed)
        return {"job": job.id}

    async def machine_jog_stop(self, p: MachineParams) -> dict[str, Any]:
        self.api.machine(p.machine).jog_stop()
        return {}

    async def machine_override(self, p: OverrideParams) -> dict[str, Any]:
        """The overrides asked for, then the overrides the board reports now in force."""
        machine = self.api.machine(p.machine)
        result: dict[str, Any] = await operations.override(machine, p.feed, p.rapid, p.spindle)
        return result

    async def machine_home(self, p: HomeParams) -> dict[str, Any]:
        with refused():
            await operations.home(self.api.machine(p.machine), _names(p.axes))
        return {}

    async def machine_zero(self, p: ZeroParams) -> dict[str, Any]:
        machine = self.api.machine(p.machine)
        with refused():
            await operations.zero(machine, {str(a): v for a, v in p.axes.items()})
        return machine.snapshot()

    async def machine_goto_zero(self, p: HomeParams) -> dict[str, Any]:
        machine = self.api.machine(p.machine)
        with refused():
            await operations.goto_zero(machine, _names(p.axes))
        return {}

    async def machine_spindle(self, p: SpindleParams) -> dict[str, Any]:
        machine = self.api.machine(p.machine)
        with refused():
            await operations.spindle(machine, p.state, p.speed)
        return {}

    async def machine_probe(self, p: ProbeParams) -> dict[str, Any]:
        """Probe with the touch plate and set work zero from it; see ProbeParams."""
        machine = self.api.machine(p.machine)
        cfg = machine.config.probe
        plate = p.plate if p.plate is not None else cfg.plate
        if plate is None:
            raise RpcError(
                -32602, "give plate (the plate's thickness, mm), or set it in [machines.probe]"
            )
        if p.kind == "xyz" and p.tool_diameter is None:
            raise RpcError(
                -32602, "an xyz probe needs tool_diameter (mm): the bit's side meets the walls"
            )
        with refused():
            return await probing.probe(
                machine,
                p.kind,
                plate,
                feed=p.feed if p.feed is not None else cfg.feed,
                max_travel=p.max_travel if p.max_travel is not None else cfg.max_travel,
                retract=p.retract if p.retract is not None else cfg.retract,
                tool_diameter=p.tool_diameter or 0.0,
                confirmed=p.confirmed,
                wait=p.wait,
            )

    async def machine_laser_test(self, p: LaserTestParams) -> dict[str, Any]:
        """Fire standing still for at most 2 s, then always off (operations.laser_test)."""
        with refused():
            await operations.laser_test(self.api.machine(p.machine), p.power, p.duration_s)
        return {}

    async def machine_frame(self, p: FrameParams) -> dict[str, Any]:
        """Trace the file's bounding box, as a job (operations.frame)."""
        machine = self.api.machine(p.machine)
        path = await self.api.resolve(p.file)
        with refused():
            job = await operations.frame(
                machine, path, p.power, p.feed, pool=self.api.daemon.workers
            )
        return {"job": job.id}

    async def machine_safety_door(self, p: MachineParams) -> dict[str, Any]:
        self.api.machine(p.machine).safety_door()
        return {}


def _names(axes: list[HomeAxis] | None) -> list[str] | None:
    return None if axes is None else [str(a) for a in axes]


def register(m: Methods, api: Api) -> None:
    h = MachineMethods(api)
    m.register("machine.list", None, h.machine_list)
    m.register("machine.status", MachineParams, h.machine_status)
    m.register("machine.connect", MachineParams, h.machine_connect)
    m.register("machine.disconnect", MachineParams, h.machine_disconnect)
    m.register("machine.send", SendParams, h.machine_send)
    m.register("machine.maintenance", SendParams, h.machine_maintenance)
    m.register("machine.feedhold", MachineParams, h.machine_feedhold, immediate=True)
    m.register("machine.cycle_start", MachineParams, h.machine_cycle_start, immediate=True)
    m.register("machine.queue_flush", MachineParams, h.machine_queue_flush, immediate=True)
    m.register("machine.job_kill", MachineParams, h.machine_job_kill, immediate=True)
    m.register("machine.reset", MachineParams, h.machine_reset)
    m.register("machine.clear", MachineParams, h.machine_clear)
    m.register("machine.alarm", MachineParams, h.machine_alarm)
    m.register("machine.shutdown", MachineParams, h.machine_shutdown)
    m.register("machine.jog", JogParams, h.machine_jog)
    m.register("machine.jog_stop", MachineParams, h.machine_jog_stop, immediate=True)
    # Not immediate: it waits for the report that shows the overrides now in force.
    m.register("machine.override", OverrideParams, h.machine_override)
    m.register("machine.home", HomeParams, h.machine_home)
    m.register("machine.zero", ZeroParams, h.machine_zero)
    m.register("machine.goto_zero", HomeParams, h.machine_goto_zero)
    m.register("machine.spindle", SpindleParams, h.machine_spindle)
    m.register("machine.probe", ProbeParams, h.machine_probe)
    m.register("machine.safety_door", MachineParams, h.machine_safety_door, immediate=True)
    m.register("machine.laser_test", LaserTestParams, h.machine_laser_test)
    m.register("machine.frame", FrameParams, h.machine_frame)
