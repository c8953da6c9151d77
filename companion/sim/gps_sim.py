"""The simulated GPS receiver: the true position and velocity in, NMEA epochs out.

One module per simulated device (see `companion.sim.imu_sim`). Pure and deterministic given a
``numpy.random.Generator``: the world (`companion.sim.world`) calls `GpsSim.epoch` at the
receiver's rate and delivers each epoch after its drawn latency.
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.core.mathutil import clamp
from companion.drivers.gps_encoder import encode_epoch
from companion.drivers.gps_solution import GpsSolution
from companion.drivers.nmea_sentences import DEFAULT_SENTENCES, TALKERS
from companion.sim.imu_model import independent_stream

__all__ = ["GpsSim", "GpsSimConfig"]

_WGS84_A_M = 6378137.0
_WGS84_E2 = 6.69437999014e-3


def _metres_to_degrees(lat_deg: float, north_m: float, east_m: float) -> tuple[float, float]:
    """Small NED offsets to latitude/longitude offsets with the WGS84 radii of curvature."""
    lat = math.radians(lat_deg)
    sin2 = math.sin(lat) ** 2
    meridian_m = _WGS84_A_M * (1 - _WGS84_E2) / (1 - _WGS84_E2 * sin2) ** 1.5
    normal_m = _WGS84_A_M / math.sqrt(1 - _WGS84_E2 * sin2)
    east_radius_m = max(normal_m * math.cos(lat), 1.0)
    return math.degrees(north_m / meridian_m), math.degrees(east_m / east_radius_m)



@dataclass(frozen=True, slots=True)
class GpsSimConfig:
    """What the simulated receiver outputs and how wrong it is (1-sigma values)."""

    talker: str = "GP"
    sentences: tuple[str, ...] = DEFAULT_SENTENCES
    ashtech_pos: bool = False
    fix: int = 1
    sats: int = 9
    hdop: float = 0.9
    pdop: float = 1.6
    vdop: float = 1.3
    tdop: float = 0.8
    horiz_white_m: float = 0.8
    vert_white_m: float = 1.5
    horiz_walk_m_sqrt_s: float = 0.1
    """Random-walk part of the position error (slowly wandering, like real GPS)."""
    vert_walk_m_sqrt_s: float = 0.15
    vel_noise_m_s: float = 0.05
    geoid_sep_m: float = 0.0
    """Ellipsoid minus MSL; 0 matches a flight model whose altitudes are ellipsoidal."""
    date: dt.date = field(default_factory=lambda: dt.date(2003, 6, 1))
    """UTC date of second 0 of the simulation."""
    rate_hz: float = 10.0
    """Epochs per second (1, 5 or 10 in the profiles; the world needs 100 / rate whole)."""
    latency_s: float = 0.05
    """Mean age of an epoch when its bytes arrive (the world delays each epoch by a draw)."""
    latency_jitter_s: float = 0.0
    """Spread (1 sigma) of that age, epoch by epoch; never below zero."""
    gm_horiz_m: float = 0.0
    """Sigma of the first-order Gauss-Markov position error, per horizontal axis."""
    gm_vert_m: float = 0.0
    gm_tau_s: float = 300.0
    multipath_per_h: float = 0.0
    """Rate of multipath jumps: rare steps of the position error that then decay."""
    multipath_m: float = 0.0
    """Sigma of a jump, per horizontal axis (vertical: 1.5 times)."""
    multipath_tau_s: float = 20.0
    outage_per_h: float = 0.0
    """Rate of outages (no fix) and their length."""
    outage_s: float = 0.0
    heading_std_deg: float = 0.0
    """1-sigma of the true heading a dual-antenna receiver sends (``HDT`` in ``sentences``);
    white, epoch to epoch."""
    heading_mount_deg: float = 0.0
    """1-sigma of the antenna baseline's yaw error on the airframe, drawn once: what the
    ground measurement of the baseline's direction left (the receiver cannot see it)."""

    def __post_init__(self) -> None:
        every = 100.0 / self.rate_hz if self.rate_hz > 0 else math.inf
        if not (1 <= every <= 100 and abs(every - round(every)) < 1e-9):
            raise ValueError(f"GpsSimConfig.rate_hz must divide 100 Hz (1, 2, 5, 10 ...), "
                             f"got {self.rate_hz!r}")
        for name in ("latency_s", "latency_jitter_s", "gm_horiz_m", "gm_vert_m",
                     "multipath_per_h", "multipath_m", "outage_per_h", "outage_s",
                     "heading_std_deg", "heading_mount_deg"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"GpsSimConfig.{name} must be finite and >= 0, got {value!r}")
        for name in ("gm_tau_s", "multipath_tau_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"GpsSimConfig.{name} must be > 0, got {value!r}")

    @property
    def perfect(self) -> bool:
        """No error, no jitter, no outage: what `--no-noise` asks of the receiver."""
        return not (self.horiz_white_m or self.vert_white_m or self.horiz_walk_m_sqrt_s
                    or self.vert_walk_m_sqrt_s or self.vel_noise_m_s or self.latency_jitter_s
                    or self.gm_horiz_m or self.gm_vert_m or self.multipath_per_h
                    or self.outage_per_h or self.heading_std_deg or self.heading_mount_deg)

    @property
    def expected_sentences(self) -> tuple[str, ...]:
        """The sentence set one epoch holds: pass it to ``NmeaDecoder(expected_sentences=...)``."""
        return tuple(self.sentences) + (("POS",) if self.ashtech_pos else ())


class GpsSim:
    """Receiver epochs (``config.rate_hz``) from the true position and NED velocity.

    The original error model (white plus random-walk position error, white velocity noise)
    draws from ``rng`` as it always did; the newer terms (Gauss-Markov error, multipath jumps,
    outages, latency jitter) draw from an independent stream jumped off it, so a profile
    without them reproduces earlier flights bit for bit.
    """

    RATE_HZ = 10

    def __init__(self, rng: np.random.Generator, config: GpsSimConfig | None = None) -> None:
        self.rng = rng
        self.config = cfg = config or GpsSimConfig()
        if cfg.talker not in TALKERS:
            raise ValueError(f"GpsSimConfig.talker must be one of {TALKERS}, got {cfg.talker!r}")
        self._walk_m = [0.0, 0.0, 0.0]
        self._extra = independent_stream(rng)
        self._gm_m = [0.0, 0.0, 0.0]
        self._gm_started = False
        self._multipath_m = [0.0, 0.0, 0.0]
        self._outage_until_s = -math.inf
        self._last_utc_s: float | None = None
        self.last_solution: GpsSolution | None = None
        """The solution encoded by the last call, before the text rounding."""
        self.last_latency_s = cfg.latency_s
        """How late the last epoch is to be delivered (the world's delay for it)."""
        self.last_error_ned_m = (0.0, 0.0, 0.0)
        """Position error of the last epoch, north, east, down (m)."""
        self.in_outage = False
        """Whether the last epoch fell in an outage (no fix)."""
        self.outages = 0
        self._heading_rng: np.random.Generator | None = None
        self.heading_mount_deg = 0.0
        """The baseline's drawn yaw error on the airframe (deg; 0 without HDT)."""
        if "HDT" in cfg.sentences:
            # a stream of its own, jumped off the extra one: receivers without a heading keep
            # every earlier draw
            self._heading_rng = independent_stream(self._extra)
            self.heading_mount_deg = cfg.heading_mount_deg * float(
                self._heading_rng.standard_normal())

    def epoch(
        self,
        utc_s: float,
        lat_deg: float,
        lon_deg: float,
        alt_m: float,
        vn_m_s: float,
        ve_m_s: float,
        vd_m_s: float,
        heading_deg: float | None = None,
    ) -> bytes:
        """Return one epoch's sentences; ``utc_s`` counts seconds from midnight of ``config.date``.
        ``heading_deg`` is the airframe's true heading (an HDT receiver's truth)."""
        cfg = self.config
        truth = (utc_s, lat_deg, lon_deg, alt_m, vn_m_s, ve_m_s, vd_m_s)
        if not all(math.isfinite(v) for v in truth):
            raise ValueError(f"GpsSim.epoch: inputs must be finite, got {truth!r}")
        dt_s = (
            1.0 / cfg.rate_hz if self._last_utc_s is None else max(utc_s - self._last_utc_s, 0.0)
        )
        self._last_utc_s = utc_s
        # scalar arithmetic, element for element what the array form computed (same draws,
        # same rounding): at 10 Hz numpy's per-call cost was most of an epoch
        d = self.rng.standard_normal(9).tolist()
        walk_sigma = (cfg.horiz_walk_m_sqrt_s, cfg.horiz_walk_m_sqrt_s, cfg.vert_walk_m_sqrt_s)
        white_sigma = (cfg.horiz_white_m, cfg.horiz_white_m, cfg.vert_white_m)
        sq = math.sqrt(dt_s)
        walk = self._walk_m = [self._walk_m[i] + d[i] * walk_sigma[i] * sq for i in range(3)]
        error_m = [walk[i] + d[3 + i] * white_sigma[i] for i in range(3)]
        noise = cfg.vel_noise_m_s
        velocity = (vn_m_s + d[6] * noise, ve_m_s + d[7] * noise, vd_m_s + d[8] * noise)
        outage = self._extra_terms(utc_s, dt_s, error_m)
        self.last_error_ned_m = (error_m[0], error_m[1], error_m[2])
        fix = 0 if outage else cfg.fix
        std_h = math.hypot(cfg.horiz_white_m, cfg.horiz_walk_m_sqrt_s)
        std_v = math.hypot(cfg.vert_white_m, cfg.vert_walk_m_sqrt_s)
        if cfg.gm_horiz_m or cfg.gm_vert_m:
            std_h = math.hypot(std_h, cfg.gm_horiz_m)
            std_v = math.hypot(std_v, cfg.gm_vert_m)
        days, seconds = divmod(utc_s, 86400.0)
        common: dict[str, Any] = dict(
            utc=seconds,
            date=cfg.date + dt.timedelta(days=int(days)),
            geoid_sep_m=cfg.geoid_sep_m,
            fix=fix,
            sats=cfg.sats,
            hdop=cfg.hdop,
            pdop=cfg.pdop,
            vdop=cfg.vdop,
            tdop=cfg.tdop,
            alt_std_m=std_v,
            lat_std_m=std_h,
            lon_std_m=std_h,
        )
        if fix == 0:
            # a receiver without a fix leaves position and velocity empty
            solution = GpsSolution(**common)
        else:
            north_deg, east_deg = _metres_to_degrees(lat_deg, error_m[0], error_m[1])
            vn, ve, vd = velocity
            solution = GpsSolution(
                **common,
                lat_deg=clamp(lat_deg + north_deg, -90.0, 90.0),
                lon_deg=(lon_deg + east_deg + 180.0) % 360.0 - 180.0,
                alt_m=alt_m - error_m[2],
                speed_m_s=math.hypot(vn, ve),
                course_deg=math.degrees(math.atan2(ve, vn)) % 360.0,
                vn_m_s=vn,
                ve_m_s=ve,
                vd_m_s=vd,
                heading_deg=self._heading(heading_deg),
            )
        self.last_solution = solution
        return encode_epoch(solution, cfg.talker, cfg.sentences, cfg.ashtech_pos)

    def _heading(self, true_deg: float | None) -> float | None:
        """The baseline's heading as the receiver reports it (None: no HDT, or no truth)."""
        rng = self._heading_rng
        if rng is None or true_deg is None or not math.isfinite(true_deg):
            return None
        noise = self.config.heading_std_deg * float(rng.standard_normal())
        return (true_deg + self.heading_mount_deg + noise) % 360.0

    def _extra_terms(self, utc_s: float, dt_s: float, error_m: list[float]) -> bool:
        """Add the correlated and multipath errors to ``error_m``, draw this epoch's latency;
        return whether the epoch falls in an outage."""
        cfg = self.config
        extra = self._extra
        if cfg.latency_jitter_s:
            self.last_latency_s = max(0.0, cfg.latency_s
                                      + cfg.latency_jitter_s * float(extra.standard_normal()))
        else:
            self.last_latency_s = cfg.latency_s
        if cfg.gm_horiz_m or cfg.gm_vert_m:
            sigma = (cfg.gm_horiz_m, cfg.gm_horiz_m, cfg.gm_vert_m)
            n = extra.standard_normal(3)
            if not self._gm_started:  # start from the stationary distribution
                self._gm_m = [sigma[i] * float(n[i]) for i in range(3)]
                self._gm_started = True
            else:
                phi = math.exp(-dt_s / cfg.gm_tau_s)
                q = math.sqrt(1.0 - phi * phi)
                self._gm_m = [phi * self._gm_m[i] + q * sigma[i] * float(n[i]) for i in range(3)]
            error_m[:] = [error_m[i] + self._gm_m[i] for i in range(3)]
        if cfg.multipath_per_h:
            decay = math.exp(-dt_s / cfg.multipath_tau_s)
            self._multipath_m = [m * decay for m in self._multipath_m]
            if extra.random() < cfg.multipath_per_h / 3600.0 * dt_s:
                jump = extra.standard_normal(3) * cfg.multipath_m * np.array([1.0, 1.0, 1.5])
                self._multipath_m = [self._multipath_m[i] + float(jump[i]) for i in range(3)]
            error_m[:] = [error_m[i] + self._multipath_m[i] for i in range(3)]
        outage = utc_s < self._outage_until_s
        if not outage and cfg.outage_per_h and cfg.outage_s:
            if extra.random() < cfg.outage_per_h / 3600.0 * dt_s:
                self._outage_until_s = utc_s + cfg.outage_s
                self.outages += 1
                outage = True
        self.in_outage = outage
        return outage

