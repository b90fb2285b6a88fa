"""tests/service boots a container: `make service-test` runs it (HOSTD_SERVICE_TEST=1),
`make unit` leaves it to that target (its first run builds a Debian root)."""

from __future__ import annotations

import os

from tests.mqtt.conftest import broker  # noqa: F401  (the MQTT tests' real mosquitto)

collect_ignore_glob = [] if os.environ.get("HOSTD_SERVICE_TEST") == "1" else ["test_*.py"]
