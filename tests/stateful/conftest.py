"""Quiet logs: a state machine runs thousands of steps; warnings and errors still show."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest
import structlog

from tests.conftest import suite_logging


@pytest.fixture(autouse=True)
def warnings_only() -> Iterator[None]:
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    yield
    suite_logging()
