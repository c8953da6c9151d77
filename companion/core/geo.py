"""WGS-84 geodetic <-> local NED conversions.

The simulator reports positions both as geodetic coordinates (what a GPS receiver gives) and as
north/east/down metres from the start point (what an estimator integrates). Both views must come
from one definition or the estimator benchmark would score our own conversion error, so every
part of the project that turns a GPS fix into NED metres should use :class:`NedFrame`.

The local frame is the tangent plane at the reference point (the usual "local NED" of
navigation texts): down is along the ellipsoid normal at the reference, so a point at constant
altitude far away has a slightly positive ``down_m`` (earth curvature, about 0.08 m at 1 km).
Altitudes are heights above the WGS-84 ellipsoid; the simulator has no geoid, so that is also
its mean sea level.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

WGS84_A_M = 6378137.0
"""Semi-major axis of the WGS-84 ellipsoid."""
WGS84_F = 1.0 / 298.257223563
"""Flattening of the WGS-84 ellipsoid."""
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
"""First eccentricity squared."""
WGS84_B_M = WGS84_A_M * (1.0 - WGS84_F)
"""Semi-minor axis."""
_EP2 = WGS84_E2 / (1.0 - WGS84_E2)  # second eccentricity squared

Vec3 = tuple[float, float, float]


def _check_geodetic(lat_deg: float, lon_deg: float, alt_m: float, where: str) -> None:
    if -90.0 <= lat_deg <= 90.0 and -180.0 <= lon_deg <= 360.0 and -1.0e5 < alt_m < 1.0e6:
        return  # in range is finite too (NaN and infinity fail every comparison)
    for name, value in (("lat_deg", lat_deg), ("lon_deg", lon_deg), ("alt_m", alt_m)):
        if not math.isfinite(value):
            raise ValueError(f"{where}: {name} must be finite, got {value!r}")
    if not -90.0 <= lat_deg <= 90.0:
        raise ValueError(f"{where}: lat_deg must be within -90..90, got {lat_deg!r}")
    if not -180.0 <= lon_deg <= 360.0:
        raise ValueError(f"{where}: lon_deg must be within -180..360, got {lon_deg!r}")
    if not -1.0e5 < alt_m < 1.0e6:
        raise ValueError(f"{where}: alt_m must be within -100 km..1000 km, got {alt_m!r}")


def geodetic_to_ecef(lat_deg: float, lon_deg: float, alt_m: float) -> Vec3:
    """Earth-centred, earth-fixed coordinates in metres of a WGS-84 geodetic point."""
    _check_geodetic(lat_deg, lon_deg, alt_m, "geodetic_to_ecef")
    lat = math.radians(lat_deg)
    lon = math.radians(lon_deg)
    slat, clat = math.sin(lat), math.cos(lat)
    n_m = WGS84_A_M / math.sqrt(1.0 - WGS84_E2 * slat * slat)
    return (
        (n_m + alt_m) * clat * math.cos(lon),
        (n_m + alt_m) * clat * math.sin(lon),
        (n_m * (1.0 - WGS84_E2) + alt_m) * slat,
    )


def ecef_to_geodetic(x_m: float, y_m: float, z_m: float) -> Vec3:
    """Geodetic latitude/longitude (deg) and ellipsoidal height (m) of an ECEF point.

    Bowring's closed form: sub-millimetre for any point within a few hundred km of the surface,
    and no iteration whose convergence would have to be guarded.
    """
    for name, value in (("x_m", x_m), ("y_m", y_m), ("z_m", z_m)):
        if not math.isfinite(value):
            raise ValueError(f"ecef_to_geodetic: {name} must be finite, got {value!r}")
    p_m = math.hypot(x_m, y_m)
    lon = math.atan2(y_m, x_m)
    if p_m < 1e-6:  # on the polar axis the longitude is arbitrary
        lat = math.copysign(math.pi / 2.0, z_m)
        return math.degrees(lat), math.degrees(lon), abs(z_m) - WGS84_B_M
    theta = math.atan2(z_m * WGS84_A_M, p_m * WGS84_B_M)
    lat = math.atan2(
        z_m + _EP2 * WGS84_B_M * math.sin(theta) ** 3,
        p_m - WGS84_E2 * WGS84_A_M * math.cos(theta) ** 3,
    )
    slat = math.sin(lat)
    n_m = WGS84_A_M / math.sqrt(1.0 - WGS84_E2 * slat * slat)
    if abs(lat) < math.radians(80.0):
        alt_m = p_m / math.cos(lat) - n_m
    else:  # near the poles cos(lat) is small: use the z form instead
        alt_m = z_m / slat - n_m * (1.0 - WGS84_E2)
    return math.degrees(lat), math.degrees(lon), alt_m


@dataclass(frozen=True)
class NedFrame:
    """A local north-east-down frame anchored at a geodetic reference point."""

    lat0_deg: float
    lon0_deg: float
    alt0_m: float
    _rot: tuple[Vec3, Vec3, Vec3] = field(init=False, repr=False, compare=False)
    _origin: Vec3 = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        _check_geodetic(self.lat0_deg, self.lon0_deg, self.alt0_m, "NedFrame reference")
        lat = math.radians(self.lat0_deg)
        lon = math.radians(self.lon0_deg)
        slat, clat = math.sin(lat), math.cos(lat)
        slon, clon = math.sin(lon), math.cos(lon)
        # Rows: north, east, down unit vectors expressed in ECEF.
        rot = (
            (-slat * clon, -slat * slon, clat),
            (-slon, clon, 0.0),
            (-clat * clon, -clat * slon, -slat),
        )
        object.__setattr__(self, "_rot", rot)
        object.__setattr__(
            self, "_origin", geodetic_to_ecef(self.lat0_deg, self.lon0_deg, self.alt0_m)
        )

    def to_ned(self, lat_deg: float, lon_deg: float, alt_m: float) -> Vec3:
        """North, east, down metres of a geodetic point from the reference."""
        x, y, z = geodetic_to_ecef(lat_deg, lon_deg, alt_m)
        ox, oy, oz = self._origin
        dx, dy, dz = x - ox, y - oy, z - oz
        (a, b, c), (d, e, f), (g, h, i) = self._rot
        return (a * dx + b * dy + c * dz, d * dx + e * dy + f * dz, g * dx + h * dy + i * dz)

    def to_geodetic(self, north_m: float, east_m: float, down_m: float) -> Vec3:
        """Geodetic latitude/longitude (deg) and height (m) of a point given in this frame."""
        for name, value in (("north_m", north_m), ("east_m", east_m), ("down_m", down_m)):
            if not math.isfinite(value):
                raise ValueError(f"NedFrame.to_geodetic: {name} must be finite, got {value!r}")
        (a, b, c), (d, e, f), (g, h, i) = self._rot
        ox, oy, oz = self._origin
        # The rotation is orthonormal: its transpose maps NED back to ECEF.
        x = ox + a * north_m + d * east_m + g * down_m
        y = oy + b * north_m + e * east_m + h * down_m
        z = oz + c * north_m + f * east_m + i * down_m
        return ecef_to_geodetic(x, y, z)
