"""Horizon-line geometry shared by every detector, the generator, the benchmark and the overlay.

A horizon is stored as an *oriented* line in image pixels (origin top-left, y down, pixel centres
at integer coordinates): a unit normal ``n = (cos t, sin t)`` that points from the sky side to the
ground side, and a signed distance ``rho`` of the line from the image centre
``((w - 1) / 2, (h - 1) / 2)`` along that normal, so points ``p`` on it satisfy
``n . (p - centre) = rho``. Orienting the normal keeps the sky side in the representation, which is
what separates a roll of 10 deg from one of 190 deg.

With this convention an upright level horizon has ``t = 90 deg`` and the roll (counter-clockwise
positive in the image, which is the aircraft's bank angle with the right wing down positive) is
``90 deg - t``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = [
    "OrientedLine",
    "wrap_deg",
]


def wrap_deg(angle_deg: float) -> float:
    """Wrap an angle into [-180, 180) so differences of attitudes compare the short way round."""
    return (angle_deg + 180.0) % 360.0 - 180.0


@dataclass(frozen=True)
class OrientedLine:
    """A horizon line in one image, with its sky side.

    ``normal_deg`` is the direction of the sky-to-ground normal in image coordinates (y down),
    ``rho_px`` the signed distance of the line from the image centre along that normal, and
    ``width``/``height`` the image size the numbers refer to.
    """

    normal_deg: float
    rho_px: float
    width: int
    height: int

    # -- constructors -------------------------------------------------------------------------

    @classmethod
    def from_roll_offset(
        cls, roll_deg: float, offset_frac: float, width: int, height: int
    ) -> OrientedLine:
        """Build the line a camera would see at this roll and centre offset (sky on the upper side
        for |roll| < 90 deg)."""
        normal_deg = 90.0 - roll_deg
        ny = math.sin(math.radians(normal_deg))
        rho = offset_frac * height * ny
        return cls(wrap_deg(normal_deg), rho, width, height)

    @classmethod
    def from_points(
        cls, p1: tuple[float, float], p2: tuple[float, float], width: int, height: int
    ) -> OrientedLine:
        """Build the line through ``p1`` and ``p2`` with the sky on the left of ``p1 -> p2`` as
        seen on screen (so left-to-right points give an upright horizon)."""
        dx, dy = p2[0] - p1[0], p2[1] - p1[1]
        length = math.hypot(dx, dy)
        if length == 0.0:
            raise ValueError(f"horizon line needs two distinct points, got {p1} twice")
        nx, ny = -dy / length, dx / length
        cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
        rho = nx * (p1[0] - cx) + ny * (p1[1] - cy)
        return cls(math.degrees(math.atan2(ny, nx)), rho, width, height)

    # -- derived quantities -------------------------------------------------------------------

    @property
    def normal(self) -> tuple[float, float]:
        t = math.radians(self.normal_deg)
        return math.cos(t), math.sin(t)

    @property
    def centre(self) -> tuple[float, float]:
        return (self.width - 1) / 2.0, (self.height - 1) / 2.0

    @property
    def roll_deg(self) -> float:
        """Bank angle, counter-clockwise positive in the image, in [-180, 180)."""
        return wrap_deg(90.0 - self.normal_deg)

    @property
    def offset_frac(self) -> float:
        """Where the line crosses the vertical through the image centre, relative to the centre,
        as a fraction of the image height, positive below; NaN for a vertical line."""
        ny = self.normal[1]
        if abs(ny) < 1e-9:
            return math.nan
        return self.rho_px / ny / self.height

    def signed_distance(self, x: float, y: float) -> float:
        """Distance of a pixel from the line, positive on the ground side."""
        nx, ny = self.normal
        cx, cy = self.centre
        return nx * (x - cx) + ny * (y - cy) - self.rho_px

    def flipped(self) -> OrientedLine:
        """The same line with sky and ground swapped."""
        return OrientedLine(wrap_deg(self.normal_deg + 180.0), -self.rho_px, self.width, self.height)

    def scaled(self, width: int, height: int) -> OrientedLine:
        """The same scene line in a resized copy of the image (independent x and y scales)."""
        sx = width / self.width
        sy = height / self.height
        p1, p2 = self._two_points()
        q1 = ((p1[0] + 0.5) * sx - 0.5, (p1[1] + 0.5) * sy - 0.5)
        q2 = ((p2[0] + 0.5) * sx - 0.5, (p2[1] + 0.5) * sy - 0.5)
        return OrientedLine.from_points(q1, q2, width, height)

    def rebased(self, width: int, height: int) -> OrientedLine:
        """The same pixels in an image of another size with the same origin (a crop or an
        extension at the right and bottom)."""
        if (width, height) == (self.width, self.height):
            return self
        return self.translated(0.0, 0.0, width, height)

    def translated(self, dx: float, dy: float, width: int, height: int) -> OrientedLine:
        """The same line in a crop whose origin is at ``(dx, dy)`` of this image."""
        p1, p2 = self._two_points()
        return OrientedLine.from_points(
            (p1[0] - dx, p1[1] - dy), (p2[0] - dx, p2[1] - dy), width, height
        )

    def _two_points(self) -> tuple[tuple[float, float], tuple[float, float]]:
        nx, ny = self.normal
        cx, cy = self.centre
        fx, fy = cx + nx * self.rho_px, cy + ny * self.rho_px
        half = float(max(self.width, self.height))
        # direction with the sky on the left when drawn on screen
        dx, dy = ny, -nx
        return (fx - dx * half, fy - dy * half), (fx + dx * half, fy + dy * half)

    def border_points(self) -> tuple[tuple[float, float], tuple[float, float]] | None:
        """Where the line enters and leaves the image rectangle [0, w-1] x [0, h-1], ordered so
        the sky is on the left of the first-to-second direction; None if it misses the image."""
        (x0, y0), (x1, y1) = self._two_points()
        dx, dy = x1 - x0, y1 - y0
        t_lo, t_hi = 0.0, 1.0
        xmax, ymax = self.width - 1.0, self.height - 1.0
        # Liang-Barsky clipping of the long segment against the image rectangle
        for p, q in ((-dx, x0), (dx, xmax - x0), (-dy, y0), (dy, ymax - y0)):
            if abs(p) < 1e-12:
                if q < 0:
                    return None
                continue
            t = q / p
            if p < 0:
                t_lo = max(t_lo, t)
            else:
                t_hi = min(t_hi, t)
        if t_hi - t_lo <= 1e-9:
            return None
        return (x0 + t_lo * dx, y0 + t_lo * dy), (x0 + t_hi * dx, y0 + t_hi * dy)

    def ground_fraction(self) -> float:
        """Fraction of the image area on the ground side, from the four corners' distances (exact
        for a straight line through a rectangle, computed by clipping)."""
        w, h = self.width - 1.0, self.height - 1.0
        corners = [(0.0, 0.0), (w, 0.0), (w, h), (0.0, h)]
        poly = _clip_polygon(corners, self)
        area = _polygon_area(poly)
        total = w * h
        return area / total if total > 0 else 0.0


def _clip_polygon(poly: list[tuple[float, float]], line: OrientedLine) -> list[tuple[float, float]]:
    """Keep the part of a convex polygon on the ground side (Sutherland-Hodgman, one edge)."""
    out: list[tuple[float, float]] = []
    n = len(poly)
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        da, db = line.signed_distance(*a), line.signed_distance(*b)
        if da >= 0:
            out.append(a)
        if (da >= 0) != (db >= 0):
            t = da / (da - db)
            out.append((a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])))
    return out


def _polygon_area(poly: list[tuple[float, float]]) -> float:
    if len(poly) < 3:
        return 0.0
    s = 0.0
    for i in range(len(poly)):
        x0, y0 = poly[i]
        x1, y1 = poly[(i + 1) % len(poly)]
        s += x0 * y1 - x1 * y0
    return abs(s) / 2.0
