"""Pinhole camera with radial lens distortion, and attitude from a horizon line.

The thesis corrected distortion on the edge points only, never on the whole frame, because the
point list is a small fraction of the pixels; detectors here do the same through
:meth:`CameraModel.undistort_points`, which inverts the radial model with a look-up table over the
radius (built once per model), like the thesis's implementation.

Model (OpenCV's, radial part only): for normalised undistorted coordinates ``(x, y)`` with
``r^2 = x^2 + y^2`` the lens puts the point at ``(x, y) * (1 + k1 r^2 + k2 r^4 + k3 r^6)``.
"""

from __future__ import annotations

import json
import math
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from horizon.geometry import OrientedLine

__all__ = ["CameraModel", "CameraError"]

_LUT_SIZE = 4096


class CameraError(ValueError):
    """A camera description that cannot be used (bad file, missing or impossible field)."""


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics in pixels for a ``width`` x ``height`` image, plus radial distortion.

    Frames of another size use :meth:`scaled_to`, which assumes the same field of view.
    """

    width: int
    height: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    _lut: tuple[NDArray[np.float64], NDArray[np.float64]] | None = field(
        default=None, init=False, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise CameraError(f"camera image size must be positive, got {self.width}x{self.height}")
        if not (self.fx_px > 0 and self.fy_px > 0):
            raise CameraError(f"focal lengths must be positive, got fx={self.fx_px} fy={self.fy_px}")
        for name in ("cx_px", "cy_px", "k1", "k2", "k3"):
            if not math.isfinite(getattr(self, name)):
                raise CameraError(f"camera field {name} must be finite")
        object.__setattr__(self, "_lut", self._build_lut())

    # -- construction -------------------------------------------------------------------------

    @classmethod
    def from_hfov(
        cls, width: int, height: int, hfov_deg: float, k1: float = 0.0, k2: float = 0.0
    ) -> CameraModel:
        """Square pixels, principal point at the image centre, focal length from the horizontal
        field of view: the usual guess when the camera was never calibrated."""
        if not 1.0 <= hfov_deg <= 179.0:
            raise CameraError(f"horizontal field of view must be in 1..179 deg, got {hfov_deg}")
        f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0, k1, k2)

    @classmethod
    def load(cls, path: str | Path) -> CameraModel:
        """Read a JSON or TOML file with ``width``, ``height`` and either ``fx, fy, cx, cy`` or
        ``hfov_deg``, plus optional ``k1, k2, k3``."""
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8")
        except OSError as exc:
            raise CameraError(f"{p}: cannot read camera file: {exc.strerror}") from None
        except UnicodeDecodeError as exc:
            raise CameraError(f"{p}: not text (byte offset {exc.start})") from None
        try:
            if p.suffix.lower() == ".toml":
                data = tomllib.loads(text)
            else:
                data = json.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise CameraError(f"{p}: invalid TOML: {exc}") from None
        except json.JSONDecodeError as exc:
            raise CameraError(f"{p}: invalid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}") from None
        if not isinstance(data, dict):
            raise CameraError(f"{p}: expected a table of camera fields at the top level")
        return cls.from_mapping(data, source=str(p))

    @classmethod
    def from_mapping(cls, data: dict[str, object], source: str = "camera") -> CameraModel:
        def num(key: str, default: float | None = None) -> float:
            if key not in data:
                if default is None:
                    raise CameraError(f"{source}: missing field '{key}'")
                return default
            value = data[key]
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise CameraError(f"{source}: field '{key}' must be a number, got {value!r}")
            return float(value)

        width, height = int(num("width")), int(num("height"))
        k1, k2, k3 = num("k1", 0.0), num("k2", 0.0), num("k3", 0.0)
        try:
            if "hfov_deg" in data:
                cam = cls.from_hfov(width, height, num("hfov_deg"), k1, k2)
                return replace(cam, k3=k3)
            return cls(width, height, num("fx"), num("fy"), num("cx"), num("cy"), k1, k2, k3)
        except CameraError as exc:
            if str(exc).startswith(source):
                raise
            raise CameraError(f"{source}: {exc}") from None

    def scaled_to(self, width: int, height: int) -> CameraModel:
        """The same lens for a resized image (pixel centres map as in ``cv2.resize``)."""
        if (width, height) == (self.width, self.height):
            return self
        sx, sy = width / self.width, height / self.height
        return CameraModel(
            width,
            height,
            self.fx_px * sx,
            self.fy_px * sy,
            (self.cx_px + 0.5) * sx - 0.5,
            (self.cy_px + 0.5) * sy - 0.5,
            self.k1,
            self.k2,
            self.k3,
        )

    @property
    def has_distortion(self) -> bool:
        return self.k1 != 0.0 or self.k2 != 0.0 or self.k3 != 0.0

    # -- distortion ---------------------------------------------------------------------------

    def _radial_factor(self, r2: NDArray[np.float64]) -> NDArray[np.float64]:
        return 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))

    def _max_radius_norm(self) -> float:
        corners_x = np.array([0.0, self.width - 1.0]) - self.cx_px
        corners_y = np.array([0.0, self.height - 1.0]) - self.cy_px
        rx = np.max(np.abs(corners_x)) / self.fx_px
        ry = np.max(np.abs(corners_y)) / self.fy_px
        return float(math.hypot(rx, ry))

    def _build_lut(self) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
        """Table from distorted radius to the undistorted/distorted scale, valid as long as the
        model is monotonic over the image (a lens whose model folds back is rejected)."""
        if not self.has_distortion:
            return None
        r_max = self._max_radius_norm()
        # undistorted radii spanning beyond the image so every distorted pixel is covered
        ru = np.linspace(0.0, 3.0 * r_max + 1e-6, _LUT_SIZE)
        rd = ru * self._radial_factor(ru * ru)
        increasing = np.diff(rd) > 0
        if not increasing.all():
            stop = int(np.argmin(increasing))
            ru, rd = ru[: stop + 1], rd[: stop + 1]
        if rd[-1] < r_max:
            raise CameraError(
                f"radial distortion k1={self.k1} k2={self.k2} k3={self.k3} folds back inside the "
                f"image (radius {rd[-1]:.3f} < {r_max:.3f} normalised)"
            )
        scale = np.ones_like(rd)
        scale[1:] = ru[1:] / rd[1:]
        return rd, scale

    def undistort_points(self, pts_px: NDArray[np.floating]) -> NDArray[np.float64]:
        """Map distorted pixel positions (N x 2) to where an ideal pinhole with the same
        intrinsics would have put them, through the radius look-up table."""
        pts = np.asarray(pts_px, dtype=np.float64)
        if self._lut is None:
            return pts.copy()
        rd_tab, scale_tab = self._lut
        x = (pts[:, 0] - self.cx_px) / self.fx_px
        y = (pts[:, 1] - self.cy_px) / self.fy_px
        s = np.interp(np.hypot(x, y), rd_tab, scale_tab)
        out = np.empty_like(pts)
        out[:, 0] = x * s * self.fx_px + self.cx_px
        out[:, 1] = y * s * self.fy_px + self.cy_px
        return out

    def distort_points(self, pts_px: NDArray[np.floating]) -> NDArray[np.float64]:
        """Where the lens puts ideal pinhole pixel positions (N x 2): the forward model."""
        pts = np.asarray(pts_px, dtype=np.float64)
        if not self.has_distortion:
            return pts.copy()
        x = (pts[:, 0] - self.cx_px) / self.fx_px
        y = (pts[:, 1] - self.cy_px) / self.fy_px
        f = self._radial_factor(x * x + y * y)
        out = np.empty_like(pts)
        out[:, 0] = x * f * self.fx_px + self.cx_px
        out[:, 1] = y * f * self.fy_px + self.cy_px
        return out

    def matrix(self) -> NDArray[np.float64]:
        """The 3x3 intrinsic matrix, for OpenCV functions."""
        return np.array(
            [[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]]
        )

    # -- attitude -----------------------------------------------------------------------------

    def attitude_deg(self, line: OrientedLine) -> tuple[float, float]:
        """Roll and pitch (deg) of a forward-looking camera that sees this undistorted horizon.

        Roll is the line's angle in normalised coordinates (counter-clockwise positive, right wing
        down). Pitch is positive nose up: raising the nose moves the horizon *down* in the image,
        and the horizon's distance below the principal point is ``f * tan(pitch)``. A camera
        mounted with a tilt must have that tilt added by the caller.
        """
        cam = self.scaled_to(line.width, line.height)
        nx, ny = line.normal
        cx, cy = line.centre
        # the line in normalised coordinates: (nx fx) u + (ny fy) v = rho - nx (cx'-cx) - ny (cy'-cy)
        ax, ay = nx * cam.fx_px, ny * cam.fy_px
        norm = math.hypot(ax, ay)
        rhs = line.rho_px - nx * (cam.cx_px - cx) - ny * (cam.cy_px - cy)
        dist = rhs / norm  # > 0: horizon lies on the ground side of the principal point
        roll = math.degrees(math.atan2(ax / norm, ay / norm))
        pitch = math.degrees(math.atan(dist))
        return roll, pitch
