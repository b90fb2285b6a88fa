"""The MQTT bridge: the daemon's notifications published to a broker, and commands from it.

`config.py` is the `[mqtt]` table, `topics.py` the topic names, payloads and
Home Assistant discovery (pure), `outbox.py` the bounded, coalescing queue
between the machines and the broker (pure), `publishing.py` the way out
(the machines' notifications into the outbox, the outbox to the broker),
`commands.py` the way in (a command checked, run and answered), and
`bridge.py` the connection that carries both.
"""
