"""MAVLink bridge: ground stations (QGroundControl, MAVProxy, MAVSDK, pymavlink) see the runtime
as a fixed-wing autopilot speaking MAVLink 2. See docs/ground-stations.md."""

from __future__ import annotations

from typing import TYPE_CHECKING

from companion.core.lazy import lazy_exports

if TYPE_CHECKING:
    from gcs_bridge.bridge import MavlinkBridge
    from gcs_bridge.dialect import Identity
    from gcs_bridge.signing import KeyFileError, new_key_file, read_key_file
    from gcs_bridge.transports.endpoints import (
        DEFAULT_ENDPOINT,
        Endpoint,
        EndpointError,
        parse_endpoint,
    )

_EXPORTS = {
    "MavlinkBridge": "gcs_bridge.bridge",
    "Identity": "gcs_bridge.dialect",
    "DEFAULT_ENDPOINT": "gcs_bridge.transports.endpoints",
    "Endpoint": "gcs_bridge.transports.endpoints",
    "EndpointError": "gcs_bridge.transports.endpoints",
    "parse_endpoint": "gcs_bridge.transports.endpoints",
    "KeyFileError": "gcs_bridge.signing",
    "new_key_file": "gcs_bridge.signing",
    "read_key_file": "gcs_bridge.signing",
}

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

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
