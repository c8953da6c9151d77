"""Named sensor and air profiles for SITL: which IMU, which GPS receiver, how rough the air.

Why profiles: a realistic flight needs dozens of error figures, and each must be traceable to a
datasheet or to stated reasoning (docs/sitl.md, "Sensor and air profiles", gives the source of
every number here). A flight names three profiles (`--imu-profile`, `--gps-profile`,
`--turbulence`); its run metadata records the names and the resolved numbers.

Conventions: datasheet tolerances given as "+-X" are read as 3-sigma bounds (X / 3 is the
1-sigma spread of a part drawn at random); "typical" figures are used as 1 sigma. Noise
densities become per-sample sigmas as density * sqrt(100 Hz), so the Allan deviation of a still
part at tau is density / sqrt(tau). A Gauss-Markov bias's sigma is the in-run bias
instability figure.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from companion.sim.gps_sim import GpsSimConfig
from companion.sim.imu_model import ImuSimConfig

__all__ = [
    "DEFAULT_GPS_PROFILE",
    "DEFAULT_IMU_PROFILE",
    "DEFAULT_TURBULENCE",
    "GPS_PROFILES",
    "IMU_PROFILES",
    "TURBULENCE",
    "GpsProfile",
    "ImuProfile",
    "SensorSetup",
    "gps_profile",
    "imu_profile",
    "resolve_sensors",
    "turbulence_severity",
]

G_M_S2 = 9.80665
DEG = math.pi / 180.0
SAMPLE_RATE_HZ = 100.0
_SQRT_FS = math.sqrt(SAMPLE_RATE_HZ)


@dataclass(frozen=True)
class ImuProfile:
    name: str
    part: str
    """The part (or class of part) the numbers come from."""
    config: ImuSimConfig


@dataclass(frozen=True)
class GpsProfile:
    name: str
    part: str
    config: GpsSimConfig


def _gyro_noise(density_deg_s_sqrt_hz: float) -> float:
    return density_deg_s_sqrt_hz * DEG * _SQRT_FS


def _accel_noise(density_ug_sqrt_hz: float) -> float:
    return density_ug_sqrt_hz * 1e-6 * G_M_S2 * _SQRT_FS


# Consumer MEMS: InvenSense MPU-6000 (PS-MPU-6000A-00 rev 3.4, tables 6.1 and 6.2), configured
# as flight controllers do: FS_SEL=3 (+-2000 deg/s), AFS_SEL=3 (+-16 g), DLPF_CFG=3 (42 Hz).
_CONSUMER = ImuSimConfig(
    gyro_noise_rad_s=_gyro_noise(0.005),            # rate noise spectral density 0.005 dps/rtHz
    accel_noise_m_s2=_accel_noise(400.0),           # power spectral density 400 ug/rtHz
    # initial ZRO tolerance +-20 dps is what the autopilot's at-rest gyro calibration at
    # power-up removes; what is left at take-off: assumed 0.2 dps (the warm-up drift below
    # comes on top)
    gyro_bias_sigma_rad_s=0.2 * DEG,
    # zero-g initial tolerance +-50 mg (x, y) is what the six-position accelerometer
    # calibration every autopilot asks for removes; what is left: assumed 5 mg
    accel_bias_sigma_m_s2=0.005 * G_M_S2,
    gyro_bias_walk_rad_s_sqrt_s=1e-4,               # not on the datasheet: assumed
    accel_bias_walk_m_s2_sqrt_s=1e-3,               # not on the datasheet: assumed
    gyro_bias_instability_rad_s=20.0 / 3600.0 * DEG,  # not on the datasheet: 20 deg/h assumed
    accel_bias_instability_m_s2=0.1e-3 * G_M_S2,    # not on the datasheet: 0.1 mg assumed
    bias_correlation_s=100.0,
    gyro_scale_sigma=0.03 / 3.0,                    # sensitivity scale factor tolerance +-3 %
    accel_scale_sigma=0.03 / 3.0,                   # initial calibration tolerance +-3 %
    gyro_cross_axis_sigma=0.02 / 3.0,               # cross-axis sensitivity +-2 %
    accel_cross_axis_sigma=0.02 / 3.0,              # cross-axis sensitivity +-2 %
    # installation: a foam-taped board, about 0.5 deg (assumed); the level calibration every
    # autopilot asks for (EST_TRIM_ROLL/PITCH) then reads it with the aircraft levelled to
    # about 0.1 deg (assumed), and cannot see its yaw
    misalignment_sigma_rad=0.5 * DEG,
    level_error_sigma_rad=0.1 * DEG,
    gyro_g_sensitivity_rad_s_per_m_s2=0.1 * DEG / G_M_S2,  # linear acceleration sens. 0.1 dps/g
    temperature_c=40.0, temperature_start_c=20.0, temperature_tau_s=300.0,  # assumed warm-up
    gyro_bias_temp_rad_s_per_c=20.0 / 125.0 / 3.0 * DEG,  # ZRO variation +-20 dps, -40..85 C
    accel_bias_temp_m_s2_per_c=0.035 / 70.0 / 3.0 * G_M_S2,  # zero-g change +-35 mg, 0..70 C
    gyro_scale_temp_per_c=0.02 / 125.0 / 3.0,       # scale factor variation +-2 %, -40..85 C
    accel_scale_temp_per_c=0.0002 / 3.0,            # sensitivity change +-0.02 %/C
    gyro_lsb_rad_s=DEG / 16.4,                      # 16.4 LSB/(deg/s) at FS_SEL=3
    accel_lsb_m_s2=G_M_S2 / 2048.0,                 # 2048 LSB/g at AFS_SEL=3
    gyro_range_rad_s=2000.0 * DEG,
    accel_range_m_s2=16.0 * G_M_S2,
    dlpf_hz=42.0,                                   # DLPF_CFG=3: gyro 42 Hz, accel 44 Hz
    vib_accel_m_s2=(0.1 * G_M_S2, 0.3 * G_M_S2, 0.3 * G_M_S2),  # assumed (docs/sitl.md)
    vib_gyro_rad_s=(0.6 * DEG, 0.6 * DEG, 0.6 * DEG),
    vib_ref_rpm=2400.0,
    vib_harmonics=((1.0, 1.0), (2.0, 0.6)),         # shaft imbalance, two-blade pass
)

# Tactical MEMS: Analog Devices ADIS16488A (data sheet, specifications table), 16-bit outputs
# and an on-chip decimation filter set for a 100 Hz output.
_TACTICAL = ImuSimConfig(
    gyro_noise_rad_s=_gyro_noise(0.26 / 60.0),      # angular random walk 0.26 deg/rt(h)
    accel_noise_m_s2=0.029 / 60.0 * _SQRT_FS,       # velocity random walk 0.029 m/s/rt(h)
    gyro_bias_sigma_rad_s=0.2 * DEG,                # bias repeatability 0.2 dps (1 sigma)
    accel_bias_sigma_m_s2=0.016 * G_M_S2,           # bias repeatability 16 mg (1 sigma)
    gyro_bias_walk_rad_s_sqrt_s=2e-5,               # not on the datasheet: assumed
    accel_bias_walk_m_s2_sqrt_s=1e-4,               # not on the datasheet: assumed
    gyro_bias_instability_rad_s=5.1 / 3600.0 * DEG,  # in-run bias stability 5.1 deg/h
    accel_bias_instability_m_s2=0.1e-3 * G_M_S2,    # in-run bias stability 0.1 mg
    bias_correlation_s=300.0,
    gyro_scale_sigma=0.003,                         # residual after factory calibration: assumed
    accel_scale_sigma=0.003,
    gyro_cross_axis_sigma=0.05 * DEG,               # axis-to-axis misalignment +-0.05 deg
    accel_cross_axis_sigma=0.035 * DEG,             # axis-to-axis misalignment +-0.035 deg
    misalignment_sigma_rad=0.1 * DEG,               # installation (machined bracket): assumed
    level_error_sigma_rad=0.1 * DEG,                # levelled for the level calibration: assumed
    gyro_g_sensitivity_rad_s_per_m_s2=0.009 * DEG / G_M_S2,  # linear-g effect 0.009 dps/g
    temperature_c=40.0, temperature_start_c=20.0, temperature_tau_s=600.0,
    gyro_bias_temp_rad_s_per_c=0.0025 / 3.0 * DEG,  # residual after temperature calibration
    accel_bias_temp_m_s2_per_c=0.1e-3 / 3.0 * G_M_S2,
    gyro_scale_temp_per_c=35e-6 / 3.0,              # sensitivity temperature coefficient
    accel_scale_temp_per_c=35e-6 / 3.0,
    gyro_lsb_rad_s=0.02 * DEG,                      # 16-bit output: 0.02 deg/s per LSB
    accel_lsb_m_s2=0.8e-3 * G_M_S2,                 # 16-bit output: 0.8 mg per LSB
    gyro_range_rad_s=450.0 * DEG,
    accel_range_m_s2=18.0 * G_M_S2,
    dlpf_hz=50.0,                                   # decimation filter for 100 Hz: assumed
    vib_accel_m_s2=(0.05 * G_M_S2, 0.15 * G_M_S2, 0.15 * G_M_S2),  # on isolators: assumed
    vib_gyro_rad_s=(0.3 * DEG, 0.3 * DEG, 0.3 * DEG),
    vib_ref_rpm=2400.0,
    vib_harmonics=((1.0, 1.0), (2.0, 0.6)),
)

# The thesis's unit: an Inertial Science ISIS 6-axis IMU (100 Hz frames, a slow block every
# second: the contract's format). Its data sheet is not at hand: class values of compact
# early-2000s navigation-aid IMUs, and the wire format's own LSB and range.
_ISIS = ImuSimConfig(
    gyro_noise_rad_s=_gyro_noise(0.01),
    accel_noise_m_s2=_accel_noise(150.0),
    gyro_bias_sigma_rad_s=0.05 * DEG,
    accel_bias_sigma_m_s2=5e-3 * G_M_S2,
    gyro_bias_walk_rad_s_sqrt_s=3e-5,
    accel_bias_walk_m_s2_sqrt_s=2e-4,
    gyro_bias_instability_rad_s=18.0 / 3600.0 * DEG,
    accel_bias_instability_m_s2=0.1e-3 * G_M_S2,
    bias_correlation_s=200.0,
    gyro_scale_sigma=0.005,
    accel_scale_sigma=0.003,
    gyro_cross_axis_sigma=0.003,
    accel_cross_axis_sigma=0.003,
    misalignment_sigma_rad=0.3 * DEG,
    level_error_sigma_rad=0.1 * DEG,
    gyro_g_sensitivity_rad_s_per_m_s2=0.02 * DEG / G_M_S2,
    temperature_c=40.0, temperature_start_c=20.0, temperature_tau_s=600.0,
    gyro_bias_temp_rad_s_per_c=0.002 * DEG,
    accel_bias_temp_m_s2_per_c=0.05e-3 * G_M_S2,
    gyro_scale_temp_per_c=50e-6,
    accel_scale_temp_per_c=50e-6,
    dlpf_hz=40.0,
    vib_accel_m_s2=(0.1 * G_M_S2, 0.3 * G_M_S2, 0.3 * G_M_S2),
    vib_gyro_rad_s=(0.6 * DEG, 0.6 * DEG, 0.6 * DEG),
    vib_ref_rpm=2400.0,
    vib_harmonics=((1.0, 1.0), (2.0, 0.6)),
)

_IDEAL_IMU = ImuSimConfig(gyro_noise_rad_s=0.0, accel_noise_m_s2=0.0, gyro_bias_sigma_rad_s=0.0,
                          accel_bias_sigma_m_s2=0.0, gyro_bias_walk_rad_s_sqrt_s=0.0,
                          accel_bias_walk_m_s2_sqrt_s=0.0)

IMU_PROFILES: dict[str, ImuProfile] = {
    "consumer": ImuProfile("consumer", "InvenSense MPU-6000 class (hobby flight controllers)",
                           _CONSUMER),
    "tactical": ImuProfile("tactical", "Analog Devices ADIS16488A class", _TACTICAL),
    "isis": ImuProfile("isis", "Inertial Science ISIS-IMU class (the thesis's unit)", _ISIS),
    "simple": ImuProfile("simple", "the original simple model (noise, turn-on bias, walk)",
                         ImuSimConfig()),
    "ideal": ImuProfile("ideal", "a perfect IMU (the wire format's quantisation only)",
                        _IDEAL_IMU),
}

# u-blox M8 class (NEO-M8N data sheet: 2.5 m CEP horizontal with GPS+GLONASS, 0.05 m/s
# velocity, up to 10 Hz with concurrent GNSS); latency, correlation, multipath and outages are
# not on a data sheet (docs/sitl.md).
_UBLOX = GpsSimConfig(
    horiz_white_m=0.5, vert_white_m=0.8, horiz_walk_m_sqrt_s=0.0, vert_walk_m_sqrt_s=0.0,
    vel_noise_m_s=0.05, hdop=0.8, pdop=1.4, vdop=1.1, tdop=0.8, sats=14,
    rate_hz=10.0, latency_s=0.1, latency_jitter_s=0.02,
    gm_horiz_m=2.0, gm_vert_m=3.5, gm_tau_s=300.0,
    multipath_per_h=4.0, multipath_m=1.5, multipath_tau_s=15.0,
    outage_per_h=1.0, outage_s=3.0,
)
# Ashtech DG16 class (DG14/DG16 Board & Sensor Reference Manual: +-3 m CEP autonomous with SA
# off, chapter 4; $PASHR,LTN latency typically 20..40 ms, chapter 8; update-rate options up
# to 20 Hz; the thesis reads it at 10 Hz).
_DG16 = GpsSimConfig(
    horiz_white_m=0.8, vert_white_m=1.5, horiz_walk_m_sqrt_s=0.0, vert_walk_m_sqrt_s=0.0,
    vel_noise_m_s=0.1, hdop=1.1, pdop=2.0, vdop=1.6, tdop=1.0, sats=8,
    rate_hz=10.0, latency_s=0.03, latency_jitter_s=0.006,
    gm_horiz_m=2.4, gm_vert_m=4.0, gm_tau_s=300.0,
    multipath_per_h=6.0, multipath_m=2.0, multipath_tau_s=20.0,
    outage_per_h=2.0, outage_s=5.0,
)
# A dual-antenna receiver (two RTK-capable receivers in moving-base mode, or one
# dual-antenna module) sending NMEA HDT each epoch. Its position is a standalone fix (no
# corrections from a ground base): the M8 class's errors. Its heading is the baseline's
# direction from the carrier-phase relative position of the two antennas: about that
# position's error over the baseline's length. RTK-class receivers give 0.01 m + 1 ppm CEP
# (about 5 mm 1-sigma per axis over a short baseline): 0.29 deg over 1 m (assumed). The
# baseline's direction measured against the airframe on the ground: 0.2 deg 1-sigma left
# (3.5 mm over 1 m, assumed).
_DUAL_ANTENNA = dataclasses.replace(
    _UBLOX, sentences=("GGA", "RMC", "VTG", "GSA", "GST", "HDT"), heading_std_deg=0.29,
    heading_mount_deg=0.2)
_IDEAL_GPS = GpsSimConfig(horiz_white_m=0.0, vert_white_m=0.0, horiz_walk_m_sqrt_s=0.0,
                          vert_walk_m_sqrt_s=0.0, vel_noise_m_s=0.0)

GPS_PROFILES: dict[str, GpsProfile] = {
    "ublox-m8": GpsProfile("ublox-m8", "u-blox M8 class (NEO-M8N)", _UBLOX),
    "dg16": GpsProfile("dg16", "Ashtech DG16 class (the thesis's receiver)", _DG16),
    "simple": GpsProfile("simple", "the original simple model (white + random walk, fixed "
                         "latency)", GpsSimConfig()),
    "ideal": GpsProfile("ideal", "a perfect receiver (fixed latency, no error)", _IDEAL_GPS),
    "dual-antenna": GpsProfile("dual-antenna", "a dual-antenna receiver with a 1 m baseline "
                               "(M8-class position, HDT heading)", _DUAL_ANTENNA),
}

TURBULENCE: dict[str, int] = {"none": 0, "light": 3, "moderate": 4, "severe": 6}
"""JSBSim's MIL-F-8785C severity index (probability-of-exceedance curve): JSBSim's FGWinds
names 3 light, 4 moderate and 6 severe; `FlightModel` pairs them with 15, 30, 45 kt at 20 ft."""

DEFAULT_IMU_PROFILE = "consumer"
DEFAULT_GPS_PROFILE = "ublox-m8"
DEFAULT_TURBULENCE = "moderate"


def _lookup(table: dict[str, Any], name: str, what: str) -> Any:
    try:
        return table[name]
    except KeyError:
        raise ValueError(f"unknown {what} {name!r}: choose one of {', '.join(table)}") from None


def imu_profile(name: str) -> ImuProfile:
    """The named IMU profile; ValueError listing the choices for an unknown name."""
    return _lookup(IMU_PROFILES, name, "IMU profile")  # type: ignore[no-any-return]


def gps_profile(name: str) -> GpsProfile:
    """The named GPS profile; ValueError listing the choices for an unknown name."""
    return _lookup(GPS_PROFILES, name, "GPS profile")  # type: ignore[no-any-return]


def turbulence_severity(name: str) -> int:
    """JSBSim's turbulence severity for a name; ValueError listing the choices."""
    return _lookup(TURBULENCE, name, "turbulence")  # type: ignore[no-any-return]


def perfect_gps(config: GpsSimConfig) -> GpsSimConfig:
    """The receiver without any error: same rate and mean latency, no noise, no jitter, no
    correlated error, multipath or outage."""
    return dataclasses.replace(
        config, horiz_white_m=0.0, vert_white_m=0.0, horiz_walk_m_sqrt_s=0.0,
        vert_walk_m_sqrt_s=0.0, vel_noise_m_s=0.0, latency_jitter_s=0.0, gm_horiz_m=0.0,
        gm_vert_m=0.0, multipath_per_h=0.0, outage_per_h=0.0, heading_std_deg=0.0,
        heading_mount_deg=0.0)


@dataclass(frozen=True)
class SensorSetup:
    """The sensors and air of one flight, resolved from names and overrides."""

    imu_profile: str
    gps_profile: str
    turbulence: str
    no_noise: bool
    imu: ImuSimConfig
    gps: GpsSimConfig
    turbulence_severity: int

    def metadata(self) -> dict[str, Any]:
        """Names and resolved numbers, JSON-ready (infinities as None), for run metadata."""
        def clean(value: Any) -> Any:
            if isinstance(value, float) and not math.isfinite(value):
                return None
            if isinstance(value, tuple | list):
                return [clean(v) for v in value]
            if isinstance(value, dict):
                return {k: clean(v) for k, v in value.items()}
            if isinstance(value, int | float | str | bool) or value is None:
                return value
            return str(value)

        return {"imu_profile": self.imu_profile, "gps_profile": self.gps_profile,
                "turbulence": self.turbulence, "turbulence_severity": self.turbulence_severity,
                "no_noise": self.no_noise, "imu": clean(dataclasses.asdict(self.imu)),
                "gps": clean(dataclasses.asdict(self.gps))}


def resolve_sensors(imu: str | None = None, gps: str | None = None,
                    turbulence: str | None = None, *, no_noise: bool = False,
                    gps_latency_s: float | None = None, gps_ashtech: bool = False) -> SensorSetup:
    """Profiles by name (None: the defaults) into configurations. ``no_noise`` makes both
    sensors perfect and, unless ``turbulence`` is named, the air calm; ``gps_latency_s``
    overrides the receiver's mean latency."""
    imu_name = imu or DEFAULT_IMU_PROFILE
    gps_name = gps or DEFAULT_GPS_PROFILE
    air = turbulence or ("none" if no_noise else DEFAULT_TURBULENCE)
    imu_cfg = imu_profile(imu_name).config
    gps_cfg = gps_profile(gps_name).config
    severity = turbulence_severity(air)
    if no_noise:
        imu_cfg = _IDEAL_IMU
        gps_cfg = perfect_gps(gps_cfg)
    if gps_latency_s is not None:
        if not (math.isfinite(gps_latency_s) and 0.0 <= gps_latency_s <= 1.0):
            raise ValueError(f"GPS latency must be within 0..1 s, got {gps_latency_s!r}")
        gps_cfg = dataclasses.replace(gps_cfg, latency_s=gps_latency_s)
    if gps_ashtech:
        gps_cfg = dataclasses.replace(gps_cfg, ashtech_pos=True)
    return SensorSetup(imu_name, gps_name, air, no_noise, imu_cfg, gps_cfg, severity)
