"""Choosing a detector by name, and the one-call ``detect`` entry point.

Methods are registered as (module, class) and imported on first use, so adding one is one module
and one table row.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:  # the table is read by every `companion` command's parser: no numpy for it
    import numpy as np
    from numpy.typing import NDArray

    from horizon.camera import CameraModel
    from horizon.estimate import HorizonEstimate

__all__ = ["Detector", "METHODS", "DEFAULT_METHOD", "create_detector", "detect", "method_names"]


class Detector(Protocol):
    name: str

    def detect(self, frame: NDArray[np.uint8]) -> HorizonEstimate: ...


METHODS: dict[str, tuple[str, str]] = {
    "baseline": ("horizon.baseline", "BaselineDetector"),
    "robust": ("horizon.robust", "RobustDetector"),
}
ALIASES: dict[str, str] = {"best": "robust", "thesis": "baseline"}
DEFAULT_METHOD = "robust"


def method_names() -> list[str]:
    """Registered names followed by their aliases, for help texts and argument choices."""
    return [*METHODS, *ALIASES]


def create_detector(method: str = DEFAULT_METHOD, camera: CameraModel | None = None) -> Detector:
    """A fresh detector for ``method`` (a name from :data:`METHODS` or an alias)."""
    key = ALIASES.get(method, method)
    try:
        module_name, class_name = METHODS[key]
    except KeyError:
        raise ValueError(
            f"unknown horizon method {method!r}; choose from {', '.join(method_names())}"
        ) from None
    cls = getattr(importlib.import_module(module_name), class_name)
    detector: Detector = cls(camera=camera)
    return detector


_CACHE_SIZE = 8
_cache: dict[tuple[str, CameraModel | None], Detector] = {}


def detect(
    frame: NDArray[np.uint8], method: str = DEFAULT_METHOD, camera: CameraModel | None = None
) -> HorizonEstimate:
    """Find the horizon in one BGR (or grey) frame, with no memory of earlier frames."""
    import numpy as np

    if not isinstance(frame, np.ndarray) or frame.dtype != np.uint8 or frame.ndim not in (2, 3):
        raise ValueError("frame must be a uint8 numpy array of shape (h, w) or (h, w, 3)")
    if frame.ndim == 3 and frame.shape[2] != 3:
        raise ValueError(f"colour frame must have 3 channels (BGR), got {frame.shape[2]}")
    if frame.shape[0] < 8 or frame.shape[1] < 8:
        raise ValueError(f"frame too small for horizon detection: {frame.shape[1]}x{frame.shape[0]}")
    key = (ALIASES.get(method, method), camera)
    det = _cache.get(key)
    if det is None:
        det = create_detector(method, camera)
        if len(_cache) >= _CACHE_SIZE:
            _cache.clear()
        _cache[key] = det
    return det.detect(frame)
