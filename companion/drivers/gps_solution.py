"""What one GPS receiver epoch says, in SI units: :class:`GpsSolution`.

The decoder (:mod:`companion.drivers.gps_protocol`) produces it, the simulator's encoder
(:mod:`companion.drivers.gps_encoder`) and the replay read it, the driver publishes it. It is
separate so that none of them needs the others to name the value they exchange.

Altitudes: ``GpsSolution.alt_m`` is above mean sea level (GGA). ``$PASHR,POS`` reports height
above the WGS84 ellipsoid (kept in ``alt_ellipsoid_m``); it is turned into MSL only with a geoid
separation from a GGA, of this epoch or the last one that had it.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Any

from companion.core.fastinit import fast_frozen

__all__ = ["GpsSolution"]


@fast_frozen
@dataclass(frozen=True)
class GpsSolution:
    """One receiver epoch, in SI units; None where no sentence of the epoch carried the value."""

    utc: float | None = None
    """Seconds since UTC midnight."""
    date: dt.date | None = None
    lat_deg: float | None = None
    lon_deg: float | None = None
    alt_m: float | None = None
    """Altitude above mean sea level."""
    alt_ellipsoid_m: float | None = None
    """Height above the WGS84 ellipsoid."""
    geoid_sep_m: float | None = None
    """Ellipsoid minus MSL (GGA); encode_epoch uses it to write the PASHR ellipsoid height."""
    fix: int = 0
    """0 none, 1 GPS, 2 DGPS, 3 RTK."""
    sats: int | None = None
    hdop: float | None = None
    pdop: float | None = None
    vdop: float | None = None
    tdop: float | None = None
    speed_m_s: float | None = None
    """Speed over ground."""
    course_deg: float | None = None
    """Course over ground, true, 0..360."""
    vn_m_s: float | None = None
    ve_m_s: float | None = None
    vd_m_s: float | None = None
    """Down velocity (from PASHR's vertical velocity, which is positive up)."""
    alt_std_m: float | None = None
    lat_std_m: float | None = None
    lon_std_m: float | None = None
    heading_deg: float | None = None
    """True heading of the antenna baseline, 0..360 (HDT: a dual-antenna receiver's; the
    course over ground says where the aircraft goes, this where it points)."""
    latency_s: float | None = None
    """Hand-off time minus arrival time of the epoch's first byte (decoder's clock)."""
    first_byte_t_ns: int | None = None
    handoff_t_ns: int | None = None
    sentences: tuple[str, ...] = ()
    """Addresses that made up the epoch, in arrival order (``GPGGA``, ``PASHR,POS``...)."""

    @property
    def utc_datetime(self) -> dt.datetime | None:
        """Full UTC timestamp, when an RMC gave the date."""
        if self.utc is None or self.date is None:
            return None
        midnight = dt.datetime.combine(self.date, dt.time(), tzinfo=dt.UTC)
        return midnight + dt.timedelta(seconds=self.utc)

    def to_json_dict(self) -> dict[str, Any]:
        """The fixed set of keys the tools and logs exchange (null where absent)."""
        return {
            "utc": self.utc,
            "lat_deg": self.lat_deg,
            "lon_deg": self.lon_deg,
            "alt_m": self.alt_m,
            "fix": self.fix,
            "sats": self.sats,
            "hdop": self.hdop,
            "pdop": self.pdop,
            "vdop": self.vdop,
            "speed_m_s": self.speed_m_s,
            "course_deg": self.course_deg,
            "alt_std_m": self.alt_std_m,
        }
