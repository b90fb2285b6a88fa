"""api.md, executable: every method, param, result key, topic and error code of
api-contract.json, asked of a real daemon (a simulated g2core on a pty) through the
real Unix socket and again through the web server's WebSocket /api.

Each test gathers every problem before it fails, and each problem names the method
(or topic, or code) and the key, so one run says all that is broken. Methods the
daemon does not serve yet are in contract.NOT_BUILT, asserted exactly.
"""

from __future__ import annotations

import base64
import json
import os
from collections import defaultdict
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio

from hostd.api.openrpc import dumps
from hostd.machine import probing
from hostd.sim import SimController
from hostd.sim.probing import TouchPlate
from tests.contract.clients import ContractClient, SocketClient, WebSocketClient
from tests.contract.contract import (
    ERRORS,
    LATER,
    METHODS,
    NOT_BUILT,
    NOT_YET_AS_NAMED,
    NOTIFICATIONS,
    notification_problems,
    result_problems,
)
from tests.daemon.conftest import Running
from tests.web.conftest import running_web

pytestmark = pytest.mark.asyncio

M = "sim1"
DOCS = Path(__file__).parents[2] / "docs" / "openrpc.json"
SIGNALS = {
    "lid_open": {"key": "in1", "equals": 1},
    "main_laser": {"key": "in2", "equals": 1},
}
LASER_ID = "sim2"
LASER = {"dialect": "grbl", "laser": True, "signals": {}}
MACRO = {"name": "to", "text": "G90 G0 X{x}", "params": {"x": {"min": 0, "max": 20}}}
LONG = "G21 G90\nG0 X0 Y0 Z5\n" + "".join(f"G1 X{i % 40} Y{i % 9} F600\n" for i in range(400))
TERMINAL = ("completed", "failed", "cancelled", "interrupted")


@dataclass
class Setup:
    hostd: Running
    client: ContractClient
    transport: str


@pytest_asyncio.fixture(params=["socket", "websocket"])
async def setup(request: pytest.FixtureRequest, tmp_path: Path) -> AsyncIterator[Setup]:
    machine: dict[str, Any] = {
        "signals": SIGNALS,
        "spindle_dwell": 0.05,
        "safe_z": 90.0,
        "tool_change": "pause",
    }
    # A grbl laser beside it, for the laser's methods; a macro on each.
    machine |= {"macros": [MACRO], "machines": 2, "per_machine": [{}, LASER]}
    async with running_web(tmp_path, machine=machine) as web:
        await web.hostd.idle(None)  # type: ignore[arg-type]  # idle opens its own client
        client: ContractClient
        if request.param == "socket":
            client = await SocketClient.open(web.hostd.socket)
        else:
            ws = await web.session.ws_connect(f"{web.url}/api", headers=web.auth())
            client = WebSocketClient(ws)
        try:
            yield Setup(web.hostd, client, request.param)
        finally:
            await client.close()


async def discovered(client: ContractClient) -> dict[str, dict[str, Any]]:
    answer = await client.request("rpc.discover")
    assert "result" in answer, answer
    return {m["name"]: m for m in answer["result"]["methods"]}


# -- the method table --------------------------------------------------------------------


async def test_every_contract_method_is_served_or_listed_as_not_built_yet(setup: Setup) -> None:
    served = set(await discovered(setup.client))

    missing = set(METHODS) - served
    assert missing == NOT_BUILT, (
        f"contract methods not served: {sorted(missing - NOT_BUILT)}; "
        f"served now, take them off NOT_BUILT: {sorted(NOT_BUILT - missing)}"
    )
    assert NOT_BUILT <= LATER  # only the operator's-day additions may wait
    assert set(NOT_YET_AS_NAMED) <= served & LATER


async def test_every_contract_param_is_in_rpc_discover_and_none_is_made_required(
    setup: Setup,
) -> None:
    served = await discovered(setup.client)
    problems = []
    for name, spec in METHODS.items():
        if name in NOT_BUILT:
            continue
        params = {p["name"]: p for p in served[name]["params"]}
        named = spec["required"] + spec["optional"]
        problems += [
            f"{name}: param {p!r} is not in rpc.discover" for p in named if p not in params
        ]
        problems += [
            f"{name}: param {p!r} is required, the contract says optional"
            for p, d in params.items()
            if d["required"] and p not in spec["required"]
        ]
    assert not problems, "\n".join(problems)


async def test_docs_openrpc_json_is_what_rpc_discover_serves(setup: Setup) -> None:
    answer = await setup.client.request("rpc.discover")
    assert answer["result"]["openrpc"].startswith("1.")
    assert DOCS.read_text(encoding="utf-8") == dumps(answer["result"]), (
        "docs/openrpc.json is out of date: run `make openrpc`"
    )


# -- every method called, every answer and notification checked --------------------------


@dataclass
class Scenario:
    """A client written from api.md, calling every method with valid params."""

    setup: Setup
    problems: list[str] = field(default_factory=list)
    sent: dict[str, set[str]] = field(default_factory=lambda: defaultdict(set))
    codes: set[int] = field(default_factory=set)
    seen: list[dict[str, Any]] = field(default_factory=list)

    @property
    def client(self) -> ContractClient:
        return self.setup.client

    async def ok(self, method: str, **params: Any) -> Any:
        """Call; an error is a problem. The result is checked against the contract."""
        answer = await self.client.request(method, params or None)
        if "error" in answer:
            self.problems.append(f"{method} {params}: answered the error {answer['error']}")
            return None
        self.sent[method].update(params)
        if method in METHODS:
            self.problems += result_problems(method, params, answer["result"])
        return answer["result"]

    async def fails(self, code: int, method: str, **params: Any) -> None:
        answer = await self.client.request(method, params or None)
        self.expect(code, f"{method} {params}", answer)

    async def raw(self, code: int, text: str) -> None:
        self.expect(code, f"the message {text!r}", await self.client.raw(text))

    def expect(self, code: int, what: str, answer: dict[str, Any]) -> None:
        error = answer.get("error") or {}
        if error.get("code") != code or not isinstance(error.get("message"), str):
            self.problems.append(f"error {code}: {what} was answered {answer}")
        else:
            self.codes.add(code)

    async def until(self, predicate: Callable[[dict[str, Any]], bool]) -> dict[str, Any]:
        """The first notification from now that matches; every one read is kept."""
        while True:
            message = await self.client.notifications.get()
            self.seen.append(message)
            if predicate(message):
                return message

    async def job_end(self, job: int) -> None:
        await self.until(
            lambda n: (
                n["method"] == "job"
                and n["params"]["job"]["id"] == job
                and n["params"]["job"]["state"] in TERMINAL
            )
        )

    async def fault(self, fault: str, active: bool) -> None:
        await self.until(
            lambda n: (
                n["method"] == "fault"
                and n["params"]["fault"]["id"] == fault
                and n["params"]["fault"]["active"] is active
            )
        )

    async def state(self, name: str) -> None:
        await self.until(
            lambda n: n["method"] == "status" and n["params"]["snapshot"]["state"]["name"] == name
        )

    async def idle(self) -> None:
        await self.setup.hostd.idle(None)  # type: ignore[arg-type]  # it opens its own client


async def run(s: Scenario, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every built contract method, with every param it names, on a g2core simulator."""
    sim = s.setup.hostd.daemon.sims[M]
    assert isinstance(sim, SimController)  # g2core's
    sub = await s.ok("subscribe", topics=list(NOTIFICATIONS), machine=M)
    await s.ok("daemon.info")
    await s.ok("machine.list")
    await s.ok("machine.status", machine=M)
    xvm = await s.ok("settings.get", machine=M, keys=["xvm"])
    await s.ok("settings.set", machine=M, values={"xvm": (xvm or {}).get("xvm", 6000)})
    await s.ok("machine.send", machine=M, line="G0 X1", timeout=10)
    await s.idle()
    jog = await s.ok("machine.jog", machine=M, axes={"x": 1.5}, feed=600)
    if jog:
        await s.job_end(jog["job"])
    await s.ok("machine.jog_stop", machine=M)
    await s.idle()
    await s.ok("machine.feedhold", machine=M)
    await s.ok("machine.cycle_start", machine=M)
    await s.ok("machine.queue_flush", machine=M)
    await s.idle()

    # Files: api.md's chunks (a first call, then append: true), base64, analysis.
    await s.ok("file.upload", name="part.gcode", data="G21 G90\nG1 X5 F600\n", encoding="utf-8")
    await s.ok("file.upload", name="part.gcode", data="G1 Y5\nG1 X0 Y0\n", append=True)
    text = base64.b64encode(b"G0 X1\n").decode()
    await s.ok("file.upload", name="b64.gcode", data=text, encoding="base64", append=False)
    await s.ok("file.list")
    await s.ok("file.analyze", file="part.gcode", machine=M)
    alone = await s.ok("file.analyze", file="part.gcode")
    if alone is not None and not isinstance(alone.get("duration_s"), int | float):
        s.problems.append(f"file.analyze without a machine: duration_s {alone.get('duration_s')!r}")
    await s.ok("file.delete", name="b64.gcode")

    # A job: paused, resumed, cancelled, then asked where to resume.
    await s.ok("file.upload", name="long.gcode", data=LONG)
    started = await s.ok(
        "job.start", machine=M, file="long.gcode", start_line=1, restore=True, force=False
    )
    await s.fails(1003, "job.start", machine=M, file="long.gcode")
    await s.ok("job.pause", machine=M)
    await s.ok("job.resume", machine=M)
    await s.until(  # a line the board ran, after the program's first absolute move
        lambda n: n["method"] == "job" and (n["params"]["job"]["line_executed"] or 0) >= 4
    )
    await s.ok("job.cancel", machine=M)
    if started:
        await s.job_end(started["job"])
        await s.ok("job.get", job=started["job"])
        recovery = await s.ok("job.recovery", job=started["job"])
        if recovery is not None and not all(isinstance(u, str) for u in recovery["uncertain"]):
            s.problems.append(f"job.recovery: uncertain must be [str]: {recovery['uncertain']}")
    await s.ok("job.list", machine=M, limit=10)
    await s.idle()

    # A tool change: the job holds at its M6 until the operator answers.
    await s.ok("file.upload", name="tools.gcode", data="G21 G90\nG0 X1\nT2 M6\nG0 X0\n")
    changing = await s.ok("job.start", machine=M, file="tools.gcode")
    await s.until(lambda n: n["method"] == "job" and n["params"]["job"]["state"] == "paused")
    await s.ok("job.tool_change_done", machine=M)
    if changing:
        await s.job_end(changing["job"])
    await s.idle()

    # Faults: one that forbids a job until overridden, one software clears.
    await s.ok("fault.list", machine=M)
    sim.set_input(2, 1)  # the main laser selected
    sim.set_input(1, 1)  # the lid open
    await s.fault("lid_open", True)
    await s.fails(1007, "job.start", machine=M, file="part.gcode")
    await s.ok("fault.override", machine=M, fault="lid_open", override=True)
    sim.set_input(1, 0)
    await s.fault("lid_open", False)
    sim.inject_garbage(b"\xff\xfe\x01 noise\n")
    await s.fault("serial", True)
    await s.ok("fault.clear", machine=M, fault="serial")

    # Lockouts: alarm, shutdown, panic; and what clears them.
    await s.ok("machine.alarm", machine=M)
    await s.state("ALARM")
    await s.fails(204, "machine.jog", machine=M, axes={"x": 1}, feed=100)
    await s.ok("machine.clear", machine=M)
    await s.ok("machine.shutdown", machine=M)
    await s.state("SHUTDOWN")
    await s.fails(205, "machine.send", machine=M, line="M30")
    await s.ok("machine.reset", machine=M)
    await s.ok("machine.send", machine=M, line="{panic:n}")
    await s.fails(206, "machine.send", machine=M, line="G0 X1")
    await s.ok("machine.reset", machine=M)
    await s.idle()
    await s.ok("machine.job_kill", machine=M)
    await s.idle()

    # The other errors api.md names.
    await s.fails(1005, "machine.send", machine=M, line="G5 X1")
    sim.stop_reading()
    await s.fails(1006, "machine.send", machine=M, line="{xvm:n}", timeout=0.3)
    sim.resume_reading()
    await s.fails(1001, "machine.status", machine="nosuch")
    await s.fails(1004, "job.get", job=999_999)
    await s.fails(-32601, "no.such.method")
    await s.fails(-32602, "file.delete", name="../outside")
    await s.raw(-32700, "{not json")
    await s.raw(-32600, '{"jsonrpc": "1.0", "method": "daemon.info", "id": null}')
    jobs = s.setup.hostd.api.jobs

    def bug() -> list[Any]:
        raise RuntimeError("a bug, on purpose")

    with monkeypatch.context() as patch:
        patch.setattr(jobs, "entries", bug)
        await s.fails(-32603, "file.list")
    await s.ok("daemon.info")  # the daemon goes on after a bug

    # The operator's day: spindle, home, zero, go to zero.
    await s.ok("machine.spindle", machine=M, state="cw", speed=1000)
    await s.ok("machine.spindle", machine=M, state="off")
    await s.ok("machine.override", machine=M, feed=120, spindle=90, rapid=50)
    await s.ok("macro.list")
    await s.ok("macro.list", machine=M)
    ran = await s.ok("macro.run", machine=M, name="to", params={"x": 3})
    if ran:
        await s.job_end(ran["job"])
    await s.idle()
    await s.ok("file.upload", name="box.gcode", data="G21 G90\nG0 X1 Y1\nG1 X4 Y3 F900\n")
    framed = await s.ok("machine.frame", machine=M, file="box.gcode", power=0, feed=2000)
    if framed:
        await s.job_end(framed["job"])
    await s.idle()
    await s.setup.hostd.idle(None, LASER_ID)  # type: ignore[arg-type]  # its own client
    await s.ok("machine.laser_test", machine=LASER_ID, power=2, duration_s=0.1)
    jog = await s.ok("machine.jog", machine=M, axes={"x": 2}, feed=600)
    if jog:
        await s.job_end(jog["job"])
    await s.idle()
    await s.ok("machine.home", machine=M, axes=["x", "y", "z"])
    await s.idle()
    await s.ok("machine.zero", machine=M, axes={"x": 0, "z": 0})
    await s.ok("machine.goto_zero", machine=M, axes=["x", "y"])
    await s.idle()
    # Probing: a plate 3 mm under the bit, touched to the bit first, then Z.
    monkeypatch.setattr(probing, "SETTLE", 0.0)
    sim.touch_plate(TouchPlate(top=sim.position["z"] - 3.0))
    sim.touch(reads=2)
    await s.ok(
        "machine.probe", machine=M, kind="z", plate=10.0, feed=600.0, max_travel=10.0, retract=2.0
    )
    sim.touch_plate(None)
    await s.idle()

    # Beyond the travel: 1008 on a homed machine.
    await s.ok("file.upload", name="wide.gcode", data="G21 G90\nG1 X350 F6000\nG1 X0\n")
    await s.fails(1008, "job.start", machine=M, file="wide.gcode")

    # The link: 1002 while disconnected.
    await s.ok("machine.disconnect", machine=M)
    await s.fails(1002, "machine.send", machine=M, line="{xvm:n}")
    await s.ok("machine.connect", machine=M)
    if sub:
        await s.ok("unsubscribe", subscription=sub["subscription"])
    await s.ok("daemon.info")  # every notification sent before it is queued by now
    while not s.client.notifications.empty():
        s.seen.append(s.client.notifications.get_nowait())


async def test_every_method_answers_every_key_and_every_topic_every_param(
    setup: Setup, monkeypatch: pytest.MonkeyPatch
) -> None:
    s = Scenario(setup)

    await run(s, monkeypatch)

    problems = list(s.problems)
    for name, spec in METHODS.items():
        if name in NOT_BUILT or name in NOT_YET_AS_NAMED:
            continue
        if name not in s.sent:
            problems.append(f"{name}: never answered a valid call")
            continue
        named = spec["required"] + spec["optional"]
        problems += [
            f"{name}: param {p!r} was never accepted" for p in named if p not in s.sent[name]
        ]
    topics: defaultdict[str, int] = defaultdict(int)
    for message in s.seen:
        if message["method"] in NOTIFICATIONS:
            topics[message["method"]] += 1
            problems += notification_problems(message)
    problems += [f"notification {t}: never sent" for t in NOTIFICATIONS if not topics[t]]
    problems += [f"error {code}: never checked" for code in ERRORS if code not in s.codes]
    assert not problems, f"over the {setup.transport}:\n" + "\n".join(dict.fromkeys(problems))


async def test_the_contract_copy_is_valid_json_naming_every_topic_and_code() -> None:
    """The copy the tests read is whole: a truncated file would make them check less."""
    text = (Path(__file__).parent / "api-contract.json").read_text(encoding="utf-8")
    contract = json.loads(text)
    assert contract["api"] == 1 and len(contract["methods"]) == 45
    assert set(contract["notifications"]) == {
        "status",
        "exception",
        "supervisor",
        "fault",
        "job",
        "console",
    }
    assert len(contract["errors"]) == 16


SPEC_BESIDE_CLONE = Path(__file__).resolve().parents[3] / "shared/spec/api-contract.json"


async def test_the_contract_copy_is_the_spec_beside_the_checkout() -> None:
    """The copy is the contract itself, not an old version of it.

    CI lays ../shared beside the clone, and there the two must be the same; a
    checkout without it has only the copy to go by (checked just above).
    """
    spec = SPEC_BESIDE_CLONE
    if not spec.exists():
        assert not os.environ.get("CI"), f"CI runs with {spec} beside the clone"
        return
    copy = Path(__file__).parent / "api-contract.json"
    assert json.loads(copy.read_text(encoding="utf-8")) == json.loads(
        spec.read_text(encoding="utf-8")
    ), f"tests/contract/api-contract.json differs from {spec}: copy it again"
