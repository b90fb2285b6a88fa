"""The daemon's API described as an OpenRPC document, made from the method table itself.

`rpc.discover` (the OpenRPC convention) answers it, and `make openrpc`
writes it to docs/openrpc.json (`python -m hostd.api.openrpc PATH`); a
test holds the two equal. Nothing in it is written by hand: each method's
params are its pydantic params model's JSON schema, split into OpenRPC
content descriptors (by name, as the daemon takes them), `required` as the
model says; its result schema comes from the handler's return annotation;
its description from the handler's or the params model's docstring. A
method added to the table is in the document; a param renamed in a model
is renamed in it.

What the schemas cannot say (which keys a result object holds, the
notifications, the error codes) is in docs/api.md; the contract test
(tests/contract) holds the daemon to ../shared/spec/api-contract.json.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import sys
import tempfile
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Final

from pydantic import BaseModel, TypeAdapter

from hostd.api.rpc import Method

OPENRPC: Final = "1.2.6"
REF: Final = "#/components/schemas/{model}"


def document(methods: Mapping[str, Method], *, version: str, api: int) -> dict[str, Any]:
    """The OpenRPC document of `methods`, sorted by name so that it diffs well."""
    schemas: dict[str, Any] = {}
    described = [_method(name, methods[name], schemas) for name in sorted(methods)]
    return {
        "openrpc": OPENRPC,
        "info": {
            "title": "hostd control API",
            "version": version,
            "description": (
                f"api {api}: JSON-RPC 2.0 over the Unix socket (newline-delimited) and the"
                " web server's WebSocket /api. Made from the daemon's method table"
                " (hostd/api/openrpc.py); result keys, notifications and error codes are in"
                " docs/api.md."
            ),
        },
        "methods": described,
        "components": {"schemas": dict(sorted(schemas.items()))},
    }


def _method(name: str, method: Method, schemas: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {"name": name, "paramStructure": "by-name"}
    description = _doc(method.handler) or _doc(method.params_model)
    if description:
        out["description"] = description
    out["params"] = _params(method.params_model, schemas)
    out["result"] = {"name": "result", "schema": _result(method.handler)}
    return out


def _params(model: type[BaseModel] | None, schemas: dict[str, Any]) -> list[dict[str, Any]]:
    """The model's fields as content descriptors, in the model's own order."""
    if model is None:
        return []
    schema = model.model_json_schema(ref_template=REF)
    schemas.update(schema.get("$defs", {}))
    required = set(schema.get("required", []))
    return [
        {"name": field, "required": field in required, "schema": _untitled(sub)}
        for field, sub in schema["properties"].items()
    ]


def _result(handler: Any) -> Any:
    """The JSON schema of what the handler returns, from its annotation (`{}`: any)."""
    try:
        returns = typing.get_type_hints(handler).get("return")
    except (NameError, TypeError):  # an annotation that cannot be resolved here
        return {}
    if returns is None:
        return {}
    return _untitled(TypeAdapter(returns).json_schema(ref_template=REF))


def _untitled(schema: Any) -> Any:
    """Without pydantic's generated titles ("Machine" for `machine`): they say nothing."""
    if isinstance(schema, dict):
        return {k: _untitled(v) for k, v in schema.items() if k != "title"}
    if isinstance(schema, list):
        return [_untitled(v) for v in schema]
    return schema


def _doc(obj: Any) -> str | None:
    """The first paragraph of a docstring of its own (not one inherited from a base)."""
    if obj is None:
        return None
    raw = vars(obj).get("__doc__") if isinstance(obj, type) else inspect.getdoc(obj)
    if not raw:
        return None
    return " ".join(inspect.cleandoc(raw).split("\n\n")[0].split())


def served() -> dict[str, Any]:
    """The document a daemon serves: its method table, built without starting anything."""
    from hostd import __version__
    from hostd.api.methods import API_VERSION, Api, build_methods
    from hostd.daemon import Daemon, DaemonConfig

    @dataclasses.dataclass(frozen=True)
    class Nothing:
        """A daemon of no machines: only its method table is read."""

        daemon: DaemonConfig
        machines: tuple[()] = ()

    with tempfile.TemporaryDirectory() as state:
        config = Nothing(DaemonConfig(socket=f"{state}/s", state_dir=state))
        methods = build_methods(Api(Daemon(config)))
    return document(methods, version=__version__, api=API_VERSION)


def dumps(doc: dict[str, Any]) -> str:
    return json.dumps(doc, indent=1, ensure_ascii=False) + "\n"


def main(argv: list[str]) -> int:
    """`python -m hostd.api.openrpc [PATH]`: write the document (stdout without PATH)."""
    text = dumps(served())
    if len(argv) > 1:
        Path(argv[1]).write_text(text, encoding="utf-8")
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv))
