"""Byte generators for the simulated IMU, GPS receiver and servo board, plus fault injection.

Everything here is pure and deterministic given a ``numpy.random.Generator``: callers pass the
true state and get back exactly the bytes the real device would send (per the device contract),
so the same driver code runs in SITL and in flight. Writing the bytes to pseudo-terminals at the
real rates is the SITL runner's job, not this module's.

Size: the three devices and the faults applied to their bytes share one set of conventions (a
chunk is a frame or an epoch, everything deterministic from one generator); split, each part
would restate them.
"""

from __future__ import annotations

import copy
import datetime as dt
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.core.mathutil import clamp
from companion.drivers.gps_encoder import encode_epoch
from companion.drivers.gps_solution import GpsSolution
from companion.drivers.imu_protocol import (
    CYCLE_FRAMES,
    STATUS_ACCEL_OK,
    STATUS_GYRO_OK,
    STATUS_SELF_TEST,
    ImuDecoder,
    ImuFast,
    encode_fast_frame,
    encode_slow_block,
    slow_block_words,
)
from companion.drivers.nmea_sentences import DEFAULT_SENTENCES, TALKERS
from companion.drivers.servo_protocol import (
    CH_MODE,
    CHANNELS,
    COMMAND_MAX_US,
    COMMAND_MIN_US,
    CommandDecoder,
    PilotFrame,
    ServoCommand,
    encode_pilot,
    pilot_switch_auto,
)
from companion.estimation.level import LevelTrim, level_trim
from companion.estimation.quat import GRAVITY_M_S2
from companion.sim.imu_model import ImuErrorModel, independent_stream

__all__ = [
    "FaultCounts",
    "FaultInjector",
    "FaultPlan",
    "GpsSim",
    "GpsSimConfig",
    "ImuSim",
    "ImuSimConfig",
    "ServoBoardConfig",
    "ServoBoardSim",
    "uart_misread",
]

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


def _vector3(values: Sequence[float], what: str) -> np.ndarray:
    array = np.asarray(values, dtype=float)
    if array.shape != (3,):
        raise ValueError(f"{what} needs 3 values, got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{what} must be finite, got {values!r}")
    return array


# ---------------------------------------------------------------------------------------------
# IMU


@dataclass(frozen=True, slots=True)
class ImuSimConfig:
    """Error model of the simulated IMU (1-sigma values; each frame is one 10 ms sample).

    The defaults are the original simple model (white noise, turn-on bias, bias random walk)
    and stay so: named, sourced profiles (`companion.sim.profiles`) fill in the other terms,
    which `companion.sim.imu_model` applies. Every term defaults to off.
    """

    gyro_noise_rad_s: float = 0.003
    """White noise per 100 Hz sample (a noise density times sqrt(100 Hz))."""
    accel_noise_m_s2: float = 0.03
    gyro_bias_sigma_rad_s: float = 0.005
    """Spread of the turn-on gyro bias, drawn once per simulator."""
    accel_bias_sigma_m_s2: float = 0.05
    gyro_bias_walk_rad_s_sqrt_s: float = 5e-5
    accel_bias_walk_m_s2_sqrt_s: float = 5e-4
    temperature_c: float = 35.0
    """The part's temperature once warm (constant when `temperature_start_c` is None)."""
    self_test_frames: int = 0
    """Frames at start-up flagged 'self-test running' with gyro/accel not yet ok."""
    bit_word: int = 0
    gyro_bias_instability_rad_s: float = 0.0
    """Sigma of the first-order Gauss-Markov bias (in-run bias instability)."""
    accel_bias_instability_m_s2: float = 0.0
    bias_correlation_s: float = 100.0
    """Correlation time of the Gauss-Markov biases."""
    gyro_scale_sigma: float = 0.0
    """Scale-factor error per axis (fraction, drawn at turn-on)."""
    accel_scale_sigma: float = 0.0
    gyro_cross_axis_sigma: float = 0.0
    """Cross-axis sensitivity, each off-diagonal element (fraction, drawn at turn-on)."""
    accel_cross_axis_sigma: float = 0.0
    misalignment_sigma_rad: float = 0.0
    """Mounting misalignment per axis: a fixed small rotation of the part against the body."""
    gyro_g_sensitivity_rad_s_per_m_s2: float = 0.0
    """Gyro rate error per unit specific force, each element of a 3x3 matrix."""
    temperature_start_c: float | None = None
    """Temperature at switch-on; it warms towards `temperature_c` with `temperature_tau_s`."""
    temperature_tau_s: float = 300.0
    gyro_bias_temp_rad_s_per_c: float = 0.0
    """Bias change per degree away from 25 C (sigma of the per-axis coefficient)."""
    accel_bias_temp_m_s2_per_c: float = 0.0
    gyro_scale_temp_per_c: float = 0.0
    accel_scale_temp_per_c: float = 0.0
    gyro_lsb_rad_s: float = 0.0
    """The part's own quantisation (0: none beyond the wire format's)."""
    accel_lsb_m_s2: float = 0.0
    gyro_range_rad_s: float = math.inf
    """The part's configured full scale: outputs clip there."""
    accel_range_m_s2: float = math.inf
    dlpf_hz: float = 0.0
    """The part's digital low-pass filter (-3 dB), applied to the vibration (0: none)."""
    vib_accel_m_s2: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Engine vibration amplitude per body axis at `vib_ref_rpm`, first harmonic."""
    vib_gyro_rad_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    vib_ref_rpm: float = 2400.0
    vib_harmonics: tuple[tuple[float, float], ...] = ((1.0, 1.0), (2.0, 0.6))
    """(multiple of the shaft rate, relative amplitude): shaft imbalance, blade pass ..."""
    level_error_sigma_rad: float | None = None
    """The installation was level-calibrated before the flight with the aircraft standing this
    far off level (1 sigma, roll and pitch); None: no level calibration (`ImuSim.level_calibration`)."""

    def temperature_at(self, t_s: float) -> float:
        """The part's temperature ``t_s`` after switch-on (warming exponentially)."""
        start = self.temperature_start_c
        if start is None or self.temperature_tau_s <= 0:
            return self.temperature_c
        return self.temperature_c + (start - self.temperature_c) * math.exp(
            -t_s / self.temperature_tau_s)


LEVEL_CALIBRATION_S = 5.0
"""How long the simulated level calibration reads the still part."""


@dataclass(frozen=True)
class SimLevelCalibration:
    """A simulated pre-flight level calibration: what it measured and the truth behind it."""

    trim: LevelTrim
    level_error_rad: tuple[float, float]
    """How far off level (roll, pitch) the aircraft stood: what the trim cannot know."""

    def params(self, prefix: str = "EST") -> dict[str, float]:
        return self.trim.params(prefix)

    def metadata(self) -> dict[str, float]:
        return {"trim_roll_deg": round(math.degrees(self.trim.roll_rad), 4),
                "trim_pitch_deg": round(math.degrees(self.trim.pitch_rad), 4),
                "level_error_roll_deg": round(math.degrees(self.level_error_rad[0]), 4),
                "level_error_pitch_deg": round(math.degrees(self.level_error_rad[1]), 4)}


class ImuSim:
    """100 Hz fast frames from true body rates and specific force, with the part's errors
    (`companion.sim.imu_model`) and the wire format's quantisation.

    Each counter cycle's slow block carries the mean of the previous cycle's measurements (the
    part's output before the wire format's quantisation): the block must be complete before its
    first word goes out.
    """

    RATE_HZ = 100

    def __init__(self, rng: np.random.Generator, config: ImuSimConfig | None = None) -> None:
        self.rng = rng
        self.config = cfg = config or ImuSimConfig()
        self.errors = ImuErrorModel(cfg, rng, self.RATE_HZ)
        self.frames = 0
        self._last_out: list[float] = [0.0] * 6
        self._sum = [0.0] * 6
        self._count = 0
        self._words: tuple[int, ...] = ()
        self._temperature_c = cfg.temperature_at(0.0)

    @classmethod
    def of_part(cls, rng: np.random.Generator, config: ImuSimConfig,
                part_seed: int | None = None) -> ImuSim:
        """The flight's IMU, drawn from ``rng``; with ``part_seed`` the part of the flight with
        that seed instead, switched on again (`ImuErrorModel.power_on_again`: its own turn-on
        bias and noise from ``rng``), so one part can fly on several days."""
        if part_seed is None:
            return cls(rng, config)
        imu = cls(np.random.default_rng(np.random.default_rng(part_seed).integers(2**63)),
                  config)
        imu.errors = imu.errors.power_on_again(rng)
        return imu

    @property
    def last_rates_rad_s(self) -> np.ndarray:
        """Measured (biased, noisy, not yet wire-quantised) rates of the last frame, rad/s."""
        return np.array(self._last_out[:3])

    @property
    def last_accel_m_s2(self) -> np.ndarray:
        """Measured specific force of the last frame (as the rates), m/s^2."""
        return np.array(self._last_out[3:])

    @property
    def gyro_bias_rad_s(self) -> np.ndarray:
        """The gyro bias now (turn-on, walk, instability, temperature), rad/s per axis."""
        return np.array(self.errors.total_bias(self._temperature_c)[0])

    @property
    def accel_bias_m_s2(self) -> np.ndarray:
        """The accelerometer bias now, m/s^2 per axis."""
        return np.array(self.errors.total_bias(self._temperature_c)[1])

    def temperature_at(self, t_s: float) -> float:
        """The part's temperature ``t_s`` after switch-on (its warm-up profile)."""
        return self.config.temperature_at(t_s)

    def level_calibration(self, rng: np.random.Generator,
                          seconds: float = LEVEL_CALIBRATION_S) -> SimLevelCalibration | None:
        """The level calibration a user makes before the flight, on this part (None when the
        configuration has none: `ImuSimConfig.level_error_sigma_rad`).

        The aircraft stands still, engine off, ``rng``'s draw of the levelling error off level,
        the part at its switch-on temperature. A twin of this simulator (same drawn errors,
        noise from ``rng``, so the flight's own draws do not move) sends ``seconds`` of frames;
        the driver's decoder reads them and the runtime's own calibration
        (`companion.estimation.level.level_trim`) turns them into the trims.
        """
        sigma = self.config.level_error_sigma_rad
        if sigma is None:
            return None
        roll, pitch = (float(v) for v in rng.normal(0.0, sigma, 2))
        g = GRAVITY_M_S2
        accel = (g * math.sin(pitch), -g * math.sin(roll) * math.cos(pitch),
                 -g * math.cos(roll) * math.cos(pitch))
        twin = copy.copy(self)
        twin.errors = self.errors.spare(rng)
        twin.frames, twin._sum, twin._count, twin._words = 0, [0.0] * 6, 0, ()
        decoder = ImuDecoder()
        temperature_c = self.config.temperature_at(0.0)
        rates: list[tuple[float, float, float]] = []
        accels: list[tuple[float, float, float]] = []
        for k in range(int(round(seconds * self.RATE_HZ))):
            data = twin.frame((0.0, 0.0, 0.0), accel, 0.0, temperature_c)
            for item in decoder.feed(data, k * 10_000_000):
                if isinstance(item, ImuFast) and item.gyro_ok and item.accel_ok:
                    rates.append(item.rates_rad_s)
                    accels.append(item.accel_m_s2)
        return SimLevelCalibration(level_trim(accels, rates), (roll, pitch))

    def frame(self, rates_rad_s: Sequence[float], accel_m_s2: Sequence[float],
              rpm: float = 0.0, temperature_c: float | None = None) -> bytes:
        """Advance 10 ms and return the next 20-byte fast frame.

        ``rpm`` is the propeller's (drives the vibration); ``temperature_c`` the part's now
        (None: its own warm-up profile at this frame's time).
        """
        cfg = self.config
        r0, r1, r2 = _finite3(rates_rad_s, "rates_rad_s")
        a0, a1, a2 = _finite3(accel_m_s2, "accel_m_s2")
        if temperature_c is None:
            temperature_c = cfg.temperature_at(self.frames / self.RATE_HZ)
        self._temperature_c = temperature_c
        out = self.errors.measure(r0, r1, r2, a0, a1, a2, rpm, temperature_c)
        counter = self.frames % CYCLE_FRAMES
        if counter == 0:
            self._start_cycle(out)
        if self.frames < cfg.self_test_frames:
            status = STATUS_SELF_TEST
        else:
            status = STATUS_GYRO_OK | STATUS_ACCEL_OK
        total = self._sum
        for i in range(6):
            total[i] += out[i]
        self._count += 1
        self._last_out = out  # arrays only when asked for (the properties): not per frame
        self.frames += 1
        return encode_fast_frame(counter, status, out[:3], out[3:], self._words[counter])

    def _start_cycle(self, out: list[float]) -> None:
        if self._count:
            mean = [v / self._count for v in self._sum]
        else:
            mean = list(out)
        self._sum = [0.0] * 6
        self._count = 0
        block = encode_slow_block(mean[:3], mean[3:], self._temperature_c, self.config.bit_word)
        self._words = slow_block_words(block)


def _finite3(values: Sequence[float], what: str) -> tuple[float, float, float]:
    """Three finite floats, or a ValueError naming ``what`` (scalar: numpy is slower here)."""
    try:
        x, y, z = values
        x, y, z = float(x), float(y), float(z)
    except (TypeError, ValueError):
        raise ValueError(f"{what} needs 3 values, got {values!r}") from None
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        raise ValueError(f"{what} must be finite, got {values!r}")
    return x, y, z


# ---------------------------------------------------------------------------------------------
# GPS


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


# ---------------------------------------------------------------------------------------------
# Servo board


@dataclass(frozen=True, slots=True)
class ServoBoardConfig:
    avionics_batt_start_raw: float = 100.0
    servo_batt_start_raw: float = 98.0
    avionics_drain_raw_per_h: float = 8.0
    servo_drain_raw_per_h: float = 20.0
    batt_noise_raw: float = 0.3
    command_timeout_s: float = 0.1
    """With no command frame for this long the board stops obeying the computer."""


NOISE_BLOCK = 256
"""Battery-reading noise draws taken from the board's generator at a time."""


class ServoBoardSim:
    """The board's side of the exchange: one pilot frame answers each command frame.

    The surfaces follow the computer only while the pilot's switch selects automatic mode and
    the latest (fresh) command asked for it; channels the computer leaves at 0 and the mode
    switch itself always follow the pilot.
    """

    def __init__(self, rng: np.random.Generator, config: ServoBoardConfig | None = None) -> None:
        self.rng = rng
        self.config = config or ServoBoardConfig()
        self.decoder = CommandDecoder()
        self.pilot_us: tuple[int, ...] = (1500, 1500, 1000, 1500, 1000, 1500, 1500, 1500)
        self.failsafe = False
        self.last_command: ServoCommand | None = None
        self._last_command_t_s = -math.inf
        self.answered = 0
        self._noise: list[float] = []  # standard normal draws, taken in blocks
        self._noise_at = 0

    def set_pilot(self, channels_us: Sequence[int], failsafe: bool = False) -> None:
        """Set what the RC receiver currently outputs (the scripted pilot's sticks)."""
        if len(channels_us) != CHANNELS:
            raise ValueError(f"channels_us needs {CHANNELS} values, got {len(channels_us)}")
        self.pilot_us = tuple(int(v) for v in channels_us)
        self.failsafe = failsafe

    def feed(self, data: bytes, t_s: float) -> bytes:
        """Consume bytes from the computer (at sim time ``t_s``); return the board's answers."""
        out = bytearray()
        for command in self.decoder.feed(data, int(t_s * 1e9)):
            self.last_command = command
            self._last_command_t_s = t_s
            out += encode_pilot(
                PilotFrame(
                    seq=command.seq,
                    auto_engaged=pilot_switch_auto(self.pilot_us),
                    failsafe=self.failsafe,
                    channels_us=self.pilot_us,
                    avionics_batt_raw=self._battery(
                        self.config.avionics_batt_start_raw,
                        self.config.avionics_drain_raw_per_h,
                        t_s,
                    ),
                    servo_batt_raw=self._battery(
                        self.config.servo_batt_start_raw, self.config.servo_drain_raw_per_h, t_s
                    ),
                )
            )
            self.answered += 1
        return bytes(out)

    def _battery(self, start_raw: float, drain_per_h: float, t_s: float) -> int:
        # the same numbers as one rng.normal(0, sigma) call per reading (numpy draws a block
        # and single values from one stream), without numpy's per-call cost at 100 readings/s
        at = self._noise_at
        if at >= len(self._noise):
            self._noise = self.rng.standard_normal(NOISE_BLOCK).tolist()
            at = 0
        self._noise_at = at + 1
        level = (
            start_raw
            - drain_per_h * t_s / 3600.0
            + (0.0 + self.config.batt_noise_raw * self._noise[at])
        )
        return clamp(round(level), 0, 255)

    def auto_active(self, t_s: float) -> bool:
        """Whether the computer drives the surfaces at sim time ``t_s``."""
        command = self.last_command
        return (
            command is not None
            and command.auto_requested
            and t_s - self._last_command_t_s <= self.config.command_timeout_s
            and pilot_switch_auto(self.pilot_us)
        )

    def effective_channels_us(self, t_s: float) -> tuple[int, ...]:
        """The pulse widths the servos get at sim time ``t_s``."""
        if not self.auto_active(t_s):
            return self.pilot_us
        assert self.last_command is not None
        out = list(self.pilot_us)
        for index, value in enumerate(self.last_command.channels_us):
            if value and index != CH_MODE:
                out[index] = clamp(value, COMMAND_MIN_US, COMMAND_MAX_US)
        return tuple(out)


# ---------------------------------------------------------------------------------------------
# Faults


@dataclass(frozen=True, slots=True)
class FaultPlan:
    """Faults to inject into a device's byte stream, chunk by chunk (a chunk = one frame/epoch)."""

    silence_s: tuple[tuple[float, float], ...] = ()
    """Windows [start, end) of sim time during which the device sends nothing."""
    garbage_prob: float = 0.0
    """Chance that random bytes precede a chunk."""
    garbage_len: tuple[int, int] = (1, 16)
    """Inclusive length range of a garbage burst."""
    cut_prob: float = 0.0
    """Chance that a chunk is cut short (its tail never sent)."""
    bad_checksum_prob: float = 0.0
    """Chance that one byte of a chunk (past its first two, before a trailing CR/LF) is altered,
    so its checksum no longer matches."""
    flood_s: tuple[tuple[float, float], ...] = ()
    """Windows [start, end) of sim time during which every chunk is sent `flood_factor` times:
    a babbling device, `flood_factor` times its byte rate, every copy valid."""
    flood_factor: int = 10
    wrong_baud_s: tuple[tuple[float, float], ...] = ()
    """Windows [start, end) during which the device sends at `baud_ratio` times the baud rate
    the computer's UART expects, so the computer receives what a mismatched UART makes of the
    bytes (see :func:`uart_misread`)."""
    baud_ratio: float = 2.0
    utc_step_s: tuple[tuple[float, float], ...] = ()
    """(at sim time, seconds) steps of the device's own clock: the GPS receiver's UTC jumps
    (a receiver reset, a leap second, a week-number rollover) while its fixes stay right."""

    def __post_init__(self) -> None:
        for name in ("garbage_prob", "cut_prob", "bad_checksum_prob"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"FaultPlan.{name} must be within 0..1, got {value}")
        if not 2 <= self.flood_factor <= 100:
            raise ValueError(f"FaultPlan.flood_factor must be within 2..100, got {self.flood_factor}")
        if not (0.05 <= self.baud_ratio <= 20.0) or abs(self.baud_ratio - 1.0) < 0.02:
            raise ValueError(f"FaultPlan.baud_ratio must be within 0.05..20 and not 1, got "
                             f"{self.baud_ratio}")
        for what, windows in (("flood_s", self.flood_s), ("wrong_baud_s", self.wrong_baud_s)):
            for start, end in windows:
                if not start <= end:
                    raise ValueError(f"FaultPlan.{what} window ({start}, {end}) ends before it "
                                     "starts")
        low, high = self.garbage_len
        if not 1 <= low <= high <= 4096:
            raise ValueError(
                f"FaultPlan.garbage_len must satisfy 1 <= min <= max <= 4096, got {self.garbage_len}"
            )
        for start, end in self.silence_s:
            if not start <= end:
                raise ValueError(
                    f"FaultPlan.silence_s window ({start}, {end}) ends before it starts"
                )


@dataclass(slots=True)
class FaultCounts:
    """What the injector actually did, so a test can compare it with the decoder's counters."""

    chunks: int = 0
    silenced: int = 0
    garbage_bursts: int = 0
    garbage_bytes: int = 0
    cut: int = 0
    corrupted: int = 0
    flooded: int = 0
    """Extra copies sent (chunks times flood_factor - 1)."""
    misread: int = 0
    """Chunks sent at the wrong baud rate."""


class FaultInjector:
    """Applies a :class:`FaultPlan` to successive chunks of a generated byte stream."""

    def __init__(self, plan: FaultPlan, rng: np.random.Generator) -> None:
        self.plan = plan
        self.rng = rng
        self.counts = FaultCounts()

    def apply(self, chunk: bytes, t_s: float) -> bytes:
        """Return the bytes actually sent for ``chunk`` generated at sim time ``t_s``."""
        plan = self.plan
        counts = self.counts
        counts.chunks += 1
        if any(start <= t_s < end for start, end in plan.silence_s):
            counts.silenced += 1
            return b""
        rng = self.rng
        data = bytearray(chunk)
        if plan.bad_checksum_prob and rng.random() < plan.bad_checksum_prob:
            stop = len(data.rstrip(b"\r\n"))
            if stop > 2:
                index = int(rng.integers(2, stop))
                data[index] ^= int(rng.integers(1, 256))
                counts.corrupted += 1
        if plan.cut_prob and len(data) > 1 and rng.random() < plan.cut_prob:
            del data[int(rng.integers(1, len(data))) :]
            counts.cut += 1
        if plan.garbage_prob and rng.random() < plan.garbage_prob:
            size = int(rng.integers(plan.garbage_len[0], plan.garbage_len[1] + 1))
            data[0:0] = rng.integers(0, 256, size, dtype=np.uint8).tobytes()
            counts.garbage_bursts += 1
            counts.garbage_bytes += size
        if any(start <= t_s < end for start, end in plan.wrong_baud_s):
            counts.misread += 1
            data = bytearray(uart_misread(bytes(data), plan.baud_ratio))
        if any(start <= t_s < end for start, end in plan.flood_s):
            counts.flooded += plan.flood_factor - 1
            return bytes(data) * plan.flood_factor
        return bytes(data)


def uart_misread(data: bytes, ratio: float) -> bytes:
    """What a UART receives when the sender runs at `ratio` times its baud rate (8N1 both).

    The bytes go out back to back, with the line idle (high) before and after; the receiver
    waits for a falling edge, samples the middle of its own bit times, and hands up each byte
    whose stop bit reads high. A byte whose stop bit reads low is a framing error, which a Linux
    tty without IGNPAR or PARMRK delivers as a NUL; the receiver then waits for the line to go
    high again before it looks for the next start bit. A real receiver behaves this way, so the
    garbage it produces (its length, its NULs, its accidental sync bytes) is what the driver
    meets when a device is configured for the wrong rate.
    """
    if not data:
        return b""
    bits: list[int] = []
    for byte in data:
        bits.append(0)
        bits.extend((byte >> i) & 1 for i in range(8))
        bits.append(1)
    n_tx = len(bits)
    rx_bit = ratio  # one receiver bit time, in sender bit times

    def level(t: float) -> int:
        k = math.floor(t)
        return bits[k] if 0 <= k < n_tx else 1

    out = bytearray()
    t = 0.0
    step = min(rx_bit, 1.0) / 4.0  # edge search resolution, finer than either bit time
    while t < n_tx:
        # find the next falling edge (line low while it was high just before)
        while t < n_tx and not (level(t) == 0 and level(t - step) == 1):
            t += step
        if t >= n_tx:
            break
        if level(t + 0.5 * rx_bit) != 0:  # a glitch, not a start bit
            t += step
            continue
        value = 0
        for i in range(8):
            value |= level(t + (1.5 + i) * rx_bit) << i
        stop_t = t + 9.5 * rx_bit
        if level(stop_t) == 1:
            out.append(value)
            t = stop_t
        else:
            out.append(0)  # framing error
            t = stop_t
            while t < n_tx and level(t) == 0:  # wait for the line to go idle (high)
                t += step
    return bytes(out)
