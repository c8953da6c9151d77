"""How a link's bytes travel: endpoint strings, and one transport per kind (UDP, TCP, serial).

Everything here is about moving bytes and naming where they go; nothing parses MAVLink beyond
the endpoint's settings. `base` holds the transport interface and the `TRANSPORTS` table that
picks a kind's module (imported lazily), `endpoints` the connection-string syntax.
"""
