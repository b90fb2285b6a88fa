"""api.md's names, machine-readable (api-contract.json), and what checks answers against them.

`api-contract.json` is a copy of the project's spec file
(`../shared/spec/api-contract.json`): every method, param, result key,
object key, topic and error code of api.md. It is the floor: the daemon
may add, never rename, remove or make required. Each check returns
problems as text naming the method (or topic) and the key, so a failing
test says exactly what broke.

What is not built yet is listed here, precisely, and asserted: a method
of the contract that the daemon does not serve must be in NOT_BUILT, and a
method in NOT_BUILT that the daemon serves fails the test until it is taken
off. The list can only shrink. They belong to api.md's "Additions for the
operator's day" (the contract's `stages.turn3`), built by a later issue.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Final

CONTRACT: Final[dict[str, Any]] = json.loads(
    (Path(__file__).parent / "api-contract.json").read_text(encoding="utf-8")
)
METHODS: Final[dict[str, dict[str, Any]]] = CONTRACT["methods"]
OBJECTS: Final[dict[str, list[str]]] = CONTRACT["objects"]
NOTIFICATIONS: Final[dict[str, list[str]]] = CONTRACT["notifications"]
ERRORS: Final[list[int]] = CONTRACT["errors"]
LATER: Final[frozenset[str]] = frozenset(CONTRACT["stages"]["turn3"])

# Contract methods the daemon does not serve yet (all of the operator's-day additions).
NOT_BUILT: Final[frozenset[str]] = frozenset()
# Served, but not yet as the contract says: the reason, for the day it is.
NOT_YET_AS_NAMED: Final[dict[str, str]] = {}
# Object keys of the contract no object carries yet ("object.key").
KEYS_NOT_BUILT: Final[frozenset[str]] = frozenset()


def object_problems(kind: str, value: Any, where: str) -> list[str]:
    """What `value`, a `kind` object ("snapshot", "job", "fault"), lacks of the contract."""
    if not isinstance(value, dict):
        return [f"{where}: a {kind} object, got {type(value).__name__}"]
    problems = [
        f"{where}: {kind} object has no key {key!r}"
        for key in OBJECTS[kind]
        if key not in value and f"{kind}.{key}" not in KEYS_NOT_BUILT
    ]
    for key in OBJECTS[kind]:
        if f"{kind}.{key}" in KEYS_NOT_BUILT and key in value:
            problems.append(f"{where}: {kind}.{key} is built now: take it off KEYS_NOT_BUILT")
    problems += _enums(kind, value, where)
    if kind == "snapshot":
        for i, fault in enumerate(value.get("faults") or []):
            problems += object_problems("fault", fault, f"{where}.faults[{i}]")
        if value.get("job") is not None:
            problems += object_problems("job", value["job"], f"{where}.job")
        state = value.get("state")
        if state is None and value.get("supervisor") == "disconnected":
            pass  # no board, no state: null (docs/api.md "The snapshot while disconnected")
        elif not isinstance(state, dict) or set(OBJECTS["snapshot.state"]) - set(state):
            problems.append(f"{where}: snapshot.state must have {OBJECTS['snapshot.state']}")
        elif state["name"] not in OBJECTS["state.names"]:
            problems.append(f"{where}: snapshot.state.name {state['name']!r} is not api.md's")
    if kind == "job" and value.get("error") is not None:
        missing = set(OBJECTS["job.error"]) - set(value["error"])
        if missing:
            problems.append(f"{where}: job.error has no key(s) {sorted(missing)}")
    return problems


def _enums(kind: str, value: dict[str, Any], where: str) -> list[str]:
    """The keys whose values api.md names ("job.kind", "snapshot.supervisor", ...)."""
    problems = []
    for key in ENUM_KEYS.get(kind, ()):
        allowed = OBJECTS[f"{kind}.{key}"]
        if key in value and value[key] not in allowed:
            problems.append(f"{where}: {kind}.{key} {value[key]!r} is not one of {allowed}")
    return problems


ENUM_KEYS: Final = {
    "job": ("kind", "state"),
    "fault": ("severity",),
    "snapshot": ("supervisor", "indicator"),
}


def result_problems(method: str, params: dict[str, Any], result: Any) -> list[str]:
    """What the result of `method` called with `params` lacks of the contract's result."""
    spec = METHODS[method]["result"]
    where = method
    if "object" in spec:
        if not isinstance(result, dict):
            return [f"{where}: the result must be an object, got {type(result).__name__}"]
        return [
            f"{where}: result has no key {key!r}" for key in spec["object"] if key not in result
        ]
    if "list_of" in spec or "list_of_is" in spec:
        if not isinstance(result, list):
            return [f"{where}: the result must be a list, got {type(result).__name__}"]
        if not result:
            return [f"{where}: the list is empty: nothing of it could be checked"]
        problems = []
        for i, item in enumerate(result):
            if "list_of_is" in spec:
                problems += object_problems(spec["list_of_is"], item, f"{where}[{i}]")
            elif not isinstance(item, dict):
                problems.append(f"{where}[{i}]: an object, got {type(item).__name__}")
            else:
                problems += [
                    f"{where}[{i}]: has no key {key!r}"
                    for key in spec["list_of"]
                    if key not in item
                ]
        return problems
    kind = spec["is"]
    if kind in OBJECTS:
        return object_problems(kind, result, where)
    asked = params["keys"] if kind == "map of the keys asked" else list(params["values"])
    if not isinstance(result, dict) or set(asked) - set(result):
        return [f"{where}: the result must map every key asked, {asked}, got {result!r}"]
    return []


def notification_problems(message: dict[str, Any]) -> list[str]:
    """What one notification of a contract topic lacks of its named params."""
    topic = message["method"]
    params = message.get("params")
    if not isinstance(params, dict):
        return [f"notification {topic}: params must be an object"]
    problems = [
        f"notification {topic}: params have no key {key!r}"
        for key in NOTIFICATIONS[topic]
        if key not in params
    ]
    where = f"notification {topic}"
    if topic == "status" and "snapshot" in params:
        problems += object_problems("snapshot", params["snapshot"], f"{where}.snapshot")
    if topic == "job" and "job" in params:
        problems += object_problems("job", params["job"], f"{where}.job")
    if topic == "fault" and "fault" in params:
        problems += object_problems("fault", params["fault"], f"{where}.fault")
    return problems
