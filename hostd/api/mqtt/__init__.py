"""The MQTT bridge: the daemon's notifications published to a broker, and commands from it.

`config.py` is the `[mqtt]` table, `topics.py` the topic names, payloads and
Home Assistant discovery (pure), `outbox.py` the bounded, coalescing queue
between the machines and the broker (pure), `bridge.py` the connection.
"""
