"""Horizon detection for attitude aiding (thesis chapter 6.2, rebuilt).

``detect(frame)`` finds the horizon in one BGR frame and returns a :class:`HorizonEstimate`
(line, roll, centre offset, pitch when camera intrinsics are given, quality, or an honest "no
horizon"). Methods are chosen by name: ``baseline`` is the thesis's 2003 pipeline, ``robust``
(alias ``best``) the project's best. :class:`HorizonTracker` adds temporal tracking for video.
"""

from __future__ import annotations

from horizon.camera import CameraError, CameraModel
from horizon.detector import DEFAULT_METHOD, METHODS, create_detector, detect, method_names
from horizon.estimate import HorizonEstimate
from horizon.geometry import OrientedLine
from horizon.tracking import HorizonTracker

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
