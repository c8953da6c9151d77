"""The result every detector returns, whether or not it found a horizon."""

from __future__ import annotations

import math
from dataclasses import dataclass

from horizon.camera import CameraModel
from horizon.geometry import OrientedLine

__all__ = ["HorizonEstimate"]


@dataclass(frozen=True)
class HorizonEstimate:
    """One frame's horizon.

    ``p1``/``p2`` are where the line meets the image border, in pixels of the input frame (after
    distortion correction when a camera model was given), ordered with the sky on the left of
    ``p1 -> p2`` on screen. ``roll_deg`` is counter-clockwise positive in the image (right wing
    down). ``offset_frac`` is the line's height at the image centre relative to the centre, as a
    fraction of the image height, positive below. ``pitch_deg`` (nose up positive) needs camera
    intrinsics and is None without them. ``quality`` in 0..1 says how much to trust the line; when
    ``found`` is False every geometric field is None and quality is what little evidence there was.
    """

    found: bool
    quality: float
    method: str
    width: int
    height: int
    p1: tuple[float, float] | None = None
    p2: tuple[float, float] | None = None
    roll_deg: float | None = None
    offset_frac: float | None = None
    pitch_deg: float | None = None
    line: OrientedLine | None = None

    @classmethod
    def none(cls, method: str, width: int, height: int, quality: float = 0.0) -> HorizonEstimate:
        """The honest answer for a frame without a usable horizon."""
        return cls(False, float(min(max(quality, 0.0), 1.0)), method, width, height)

    @classmethod
    def from_line(
        cls,
        line: OrientedLine,
        quality: float,
        method: str,
        camera: CameraModel | None = None,
    ) -> HorizonEstimate:
        """Fill every field from an oriented line; a line that misses the image is 'no horizon'."""
        pts = line.border_points()
        if pts is None:
            return cls.none(method, line.width, line.height, quality)
        roll = line.roll_deg
        pitch: float | None = None
        if camera is not None:
            roll, pitch = camera.attitude_deg(line)
        offset = line.offset_frac
        return cls(
            True,
            float(min(max(quality, 0.0), 1.0)),
            method,
            line.width,
            line.height,
            pts[0],
            pts[1],
            roll,
            None if math.isnan(offset) else offset,
            pitch,
            line,
        )
