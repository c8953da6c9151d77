"""Horizon detection for attitude aiding (thesis chapter 6.2, rebuilt).

``detect(frame)`` finds the horizon in one BGR frame and returns a :class:`HorizonEstimate`
(line, roll, centre offset, pitch when camera intrinsics are given, quality, or an honest "no
horizon"). Methods are chosen by name: ``baseline`` is the thesis's 2003 pipeline, ``robust``
(alias ``best``) the project's best. :class:`HorizonTracker` adds temporal tracking for video.

The names load on first use (PEP 562): importing OpenCV costs about 20 ms, which tools that
only reach ``horizon.cli`` to build their argument parser should not pay. The package has no
dependency on the runtime, so it does not share the runtime's helper for this.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from horizon.camera import CameraError, CameraModel
    from horizon.detector import (
        DEFAULT_METHOD,
        METHODS,
        create_detector,
        detect,
        method_names,
    )
    from horizon.estimate import HorizonEstimate
    from horizon.geometry import OrientedLine
    from horizon.tracking import HorizonTracker

_EXPORTS = {
    "CameraError": "horizon.camera",
    "CameraModel": "horizon.camera",
    "DEFAULT_METHOD": "horizon.detector",
    "METHODS": "horizon.detector",
    "create_detector": "horizon.detector",
    "detect": "horizon.detector",
    "method_names": "horizon.detector",
    "HorizonEstimate": "horizon.estimate",
    "OrientedLine": "horizon.geometry",
    "HorizonTracker": "horizon.tracking",
}

__all__ = [
    "CameraError",
    "CameraModel",
    "DEFAULT_METHOD",
    "METHODS",
    "HorizonEstimate",
    "HorizonTracker",
    "OrientedLine",
    "create_detector",
    "detect",
    "method_names",
]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'horizon' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)
