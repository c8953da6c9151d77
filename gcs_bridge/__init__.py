"""MAVLink bridge: ground stations (QGroundControl, MAVProxy, MAVSDK, pymavlink) see the runtime
as a fixed-wing autopilot speaking MAVLink 2. See docs/ground-stations.md."""

from __future__ import annotations

from gcs_bridge.bridge import MavlinkBridge
from gcs_bridge.dialect import Identity
from gcs_bridge.endpoints import DEFAULT_ENDPOINT, Endpoint, EndpointError, parse_endpoint
from gcs_bridge.signing import KeyFileError, new_key_file, read_key_file

__all__ = [
    "DEFAULT_ENDPOINT",
    "Endpoint",
    "EndpointError",
    "Identity",
    "KeyFileError",
    "MavlinkBridge",
    "new_key_file",
    "parse_endpoint",
    "read_key_file",
]
