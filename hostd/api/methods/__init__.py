"""Every method of the control API (../shared/spec/api.md), wired to the daemon.

One module per topic, each registering its own methods: daemon.py
(rpc.discover, daemon.info), machine.py, settings.py, files.py, jobs.py,
faults.py, subscriptions.py and macros.py. `Api` (base.py) is what they share.

Parameters are pydantic models (unknown fields refused: -32602). Errors
keep their api.md codes: the machine layer's errors carry `code`, `message`
and `data`; names that cannot be a file or a machine are -32602; a missing
machine is 1001, a missing job or file 1004. Handlers call the Machine, never
its engine.
"""

from __future__ import annotations

from hostd.api.methods import (
    daemon,
    faults,
    files,
    jobs,
    machine,
    macros,
    settings,
    subscriptions,
)
from hostd.api.methods.base import API_VERSION, Api
from hostd.api.methods.files import STORAGE, UploadParams
from hostd.api.methods.subscriptions import (
    MAX_SUBSCRIPTIONS,
    MAX_SUBSCRIPTIONS_PER_CLIENT,
    TOPICS,
    Subscriptions,
)
from hostd.api.rpc import Methods

__all__ = [
    "API_VERSION",
    "MAX_SUBSCRIPTIONS",
    "MAX_SUBSCRIPTIONS_PER_CLIENT",
    "STORAGE",
    "TOPICS",
    "Api",
    "Subscriptions",
    "UploadParams",
    "build_methods",
]

TOPIC_MODULES = (daemon, machine, settings, files, jobs, faults, subscriptions, macros)


def build_methods(api: Api) -> Methods:
    """The api.md method table: each topic registers its own."""
    m = Methods()
    for topic in TOPIC_MODULES:
        topic.register(m, api)
    api.methods = m
    return m
