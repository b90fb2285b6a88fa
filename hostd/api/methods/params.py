"""What every method's parameters share: strict, bounded, unknown fields refused.

Every number a client gives is a JSON number of its type (strict: no strings,
no booleans, no 1.0 for an integer), finite, and bounded. Unknown fields are
-32602 (Methods.register refuses a model that would accept them).
"""

from __future__ import annotations

from typing import Annotated

from pydantic import AfterValidator, BaseModel, ConfigDict, Field

from hostd.api.files import check_name
from hostd.protocol.numbers import MAX_DISTANCE, MAX_FEED, MIN_FEED

MachineId = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")]
MAX_ID = 2**53 - 1  # job and subscription ids, line numbers: exact in every JSON reader
Id = Annotated[int, Field(strict=True, ge=1, le=MAX_ID)]
Distance = Annotated[
    float, Field(strict=True, allow_inf_nan=False, ge=-MAX_DISTANCE, le=MAX_DISTANCE)
]
Feed = Annotated[float, Field(strict=True, allow_inf_nan=False, ge=MIN_FEED, le=MAX_FEED)]
# A file of the jobs directory, by a name that cannot leave it (hostd/api/files.py).
JobFile = Annotated[str, AfterValidator(check_name)]


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class MachineParams(Params):
    machine: MachineId
