"""The simulated IMU's error model: what a real part adds to the true rates and specific force.

Why its own module: `companion.sim.imu_sim.ImuSim` turns measurements into the contract's bytes;
this module decides what the measurements are, from the parameters it owns (`ImuSimConfig`,
which the named profiles of `companion.sim.profiles` fill in). The terms, in the order a sample meets them:

* mounting misalignment: the part's axes are the body axes turned by a fixed small rotation;
* scale-factor error and cross-axis sensitivity (a matrix ``I + S + C``), the scale factors
  drifting with temperature;
* engine vibration: harmonics of the propeller's shaft rate, amplitude growing with the square
  of the RPM (a rotating imbalance), attenuated by the part's digital low-pass filter and
  sampled at 100 Hz, so harmonics above 50 Hz alias exactly as they would on the real part;
* gyro g-sensitivity (rate error proportional to the specific force);
* bias = turn-on bias + random walk + first-order Gauss-Markov bias instability + temperature
  coefficient times (temperature - 25 C);
* white noise (noise density times the square root of the sample rate, so that the Allan
  deviation at tau is noise density over the square root of tau);
* clipping at the part's configured range, then the part's own quantisation (the wire format
  quantises again, at its own LSB).

Speed: the lockstep SITL runs one frame per 10 ms of simulated time and counts microseconds,
so everything per frame is scalar Python on precomputed matrices, and random numbers are drawn
in blocks. Determinism: everything comes from the generator handed in. The turn-on biases, the
random walk and the white noise come from it exactly as the original simple model drew them
(so the ``simple`` profile reproduces earlier flights bit for bit); every newer term draws from
an independent stream jumped off that generator, so enabling a term never reshuffles the others.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np

__all__ = ["CALIBRATION_TEMPERATURE_C", "ImuErrorModel", "ImuSimConfig", "dlpf_gain",
           "independent_stream", "rotation_matrix"]

CALIBRATION_TEMPERATURE_C = 25.0
"""Temperature at which a part's bias and scale factor are specified (datasheets: 25 C)."""
BLOCK_FRAMES = 256
"""Frames of random numbers drawn at once: numpy's call overhead dominates small draws."""
_MATRIX_REFRESH_C = 0.01
"""Temperature change that rebuilds the scale-factor matrices (slow: a warm-up takes minutes)."""


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



def rotation_matrix(rotvec_rad: tuple[float, float, float]) -> list[list[float]]:
    """Rotation matrix of a rotation vector (Rodrigues): maps body vectors into the part's axes."""
    x, y, z = rotvec_rad
    angle = math.sqrt(x * x + y * y + z * z)
    if angle == 0.0:
        return [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    kx, ky, kz = x / angle, y / angle, z / angle
    c, s = math.cos(angle), math.sin(angle)
    v = 1.0 - c
    # passive rotation (the frame turns by +angle): the transpose of the active matrix
    return [
        [c + kx * kx * v, kx * ky * v + kz * s, kx * kz * v - ky * s],
        [ky * kx * v - kz * s, c + ky * ky * v, ky * kz * v + kx * s],
        [kz * kx * v + ky * s, kz * ky * v - kx * s, c + kz * kz * v],
    ]


def dlpf_gain(freq_hz: float, cutoff_hz: float) -> float:
    """Magnitude of the part's digital low-pass filter at ``freq_hz``, modelled as a
    second-order Butterworth with its -3 dB point at ``cutoff_hz`` (0: no filter)."""
    if cutoff_hz <= 0.0:
        return 1.0
    r = freq_hz / cutoff_hz
    return 1.0 / math.sqrt(1.0 + r * r * r * r)


def independent_stream(rng: np.random.Generator) -> np.random.Generator:
    """A generator that never overlaps ``rng``'s stream, without drawing from ``rng``."""
    bit_generator = rng.bit_generator
    jumped = getattr(bit_generator, "jumped", None)
    if jumped is None:  # a bit generator without jump-ahead (SFC64): share the stream
        return rng
    return np.random.Generator(jumped())


def _matmul(a: list[list[float]], b: list[list[float]]) -> list[list[float]]:
    """3x3 product; written out, since a warm-up rebuilds the matrices a few times a second
    (``sum`` over a generator cost four times as much; the sums are the same)."""
    return [[a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j] for j in range(3)]
            for i in range(3)]


class ImuErrorModel:
    """One part's errors, drawn at turn-on from ``rng``; `measure` applies them to a sample.

    The true values of the drawn errors are attributes (``gyro_scale``, ``misalignment_rad``
    ...), so an evaluation can compare them with what an estimator makes of them.
    """

    def __init__(self, config: ImuSimConfig, rng: np.random.Generator, rate_hz: float) -> None:
        cfg = self.config = config
        self._rng = rng
        self.dt_s = 1.0 / rate_hz
        # the original model's draws, in its order (the `simple` profile's stream)
        self.gyro_walk_bias_rad_s = [float(v) for v in
                                     rng.normal(0.0, cfg.gyro_bias_sigma_rad_s, 3)]
        """Turn-on bias plus the random walk so far (the original model's whole bias)."""
        self.accel_walk_bias_m_s2 = [float(v) for v in
                                     rng.normal(0.0, cfg.accel_bias_sigma_m_s2, 3)]
        extra = self._extra = independent_stream(rng)
        n = extra.standard_normal
        # every turn-on draw is made whatever the profile, in a fixed order
        self.gyro_scale = (n(3) * cfg.gyro_scale_sigma).tolist()
        """Scale-factor error per axis at the calibration temperature (fraction)."""
        self.accel_scale = (n(3) * cfg.accel_scale_sigma).tolist()
        self.gyro_cross = (n(6) * cfg.gyro_cross_axis_sigma).tolist()
        """Off-diagonal sensitivities (xy, xz, yx, yz, zx, zy), fractions."""
        self.accel_cross = (n(6) * cfg.accel_cross_axis_sigma).tolist()
        self.misalignment_rad = tuple((n(3) * cfg.misalignment_sigma_rad).tolist())
        """Mounting rotation vector from body axes to the part's axes (rad)."""
        self.g_sensitivity = (n(9) * cfg.gyro_g_sensitivity_rad_s_per_m_s2).reshape(3, 3).tolist()
        """Gyro rate error per unit specific force (rad/s per m/s^2), a full 3x3 matrix."""
        self.gyro_bias_temp = (n(3) * cfg.gyro_bias_temp_rad_s_per_c).tolist()
        self.accel_bias_temp = (n(3) * cfg.accel_bias_temp_m_s2_per_c).tolist()
        self.gyro_scale_temp = (n(3) * cfg.gyro_scale_temp_per_c).tolist()
        self.accel_scale_temp = (n(3) * cfg.accel_scale_temp_per_c).tolist()
        self.gm_gyro_rad_s = (n(3) * cfg.gyro_bias_instability_rad_s).tolist()
        self.gm_accel_m_s2 = (n(3) * cfg.accel_bias_instability_m_s2).tolist()
        harmonics = tuple(cfg.vib_harmonics)
        phases = extra.uniform(0.0, 2.0 * math.pi, (max(len(harmonics), 1), 6))
        self.shaft_angle_rad = float(extra.uniform(0.0, 2.0 * math.pi))
        # a*sin(m*theta + phi) = (a cos phi) sin(m theta) + (a sin phi) cos(m theta)
        amps = list(cfg.vib_accel_m_s2) + list(cfg.vib_gyro_rad_s)
        self._vib = [(float(m), float(rel), [rel * amps[i] * math.cos(phases[h][i]) for i in range(6)],
                      [rel * amps[i] * math.sin(phases[h][i]) for i in range(6)])
                     for h, (m, rel) in enumerate(harmonics)]
        self._vib_on = any(amps) and bool(harmonics)
        self._gm_on = cfg.gyro_bias_instability_rad_s > 0 or cfg.accel_bias_instability_m_s2 > 0
        phi = math.exp(-self.dt_s / cfg.bias_correlation_s) if cfg.bias_correlation_s > 0 else 0.0
        self._gm_phi = phi
        self._gm_q_gyro = cfg.gyro_bias_instability_rad_s * math.sqrt(1.0 - phi * phi)
        self._gm_q_accel = cfg.accel_bias_instability_m_s2 * math.sqrt(1.0 - phi * phi)
        self._rotation = rotation_matrix(self.misalignment_rad)
        self._matrix_temp_c = math.nan
        self._gyro_matrix: list[list[float]] = []
        self._accel_matrix: list[list[float]] = []
        self._g_sens_on = cfg.gyro_g_sensitivity_rad_s_per_m_s2 > 0
        self._clip_on = math.isfinite(cfg.gyro_range_rad_s) or math.isfinite(cfg.accel_range_m_s2)
        self._plain = not (
            cfg.gyro_scale_sigma or cfg.accel_scale_sigma or cfg.gyro_cross_axis_sigma
            or cfg.accel_cross_axis_sigma or cfg.misalignment_sigma_rad or self._g_sens_on
            or cfg.gyro_bias_temp_rad_s_per_c or cfg.accel_bias_temp_m_s2_per_c
            or cfg.gyro_scale_temp_per_c or cfg.accel_scale_temp_per_c or self._gm_on
            or self._vib_on or cfg.gyro_lsb_rad_s or cfg.accel_lsb_m_s2 or self._clip_on)
        """No term beyond the original bias, walk and noise: the fast path, bit for bit the
        original arithmetic."""
        self._block: list[list[float]] = []
        self._extra_block: list[list[float]] = []
        self._row = BLOCK_FRAMES
        self.temperature_c = math.nan
        self.vibration = [0.0] * 6
        """The last sample's vibration (accel m/s^2, gyro rad/s), as the part saw it."""

    def spare(self, rng: np.random.Generator) -> ImuErrorModel:
        """This part as it is now (every drawn error and bias state) with noise from ``rng``:
        measurements outside the flight, such as the simulated level calibration, then leave
        the flight's own draws where they were."""
        twin = copy.copy(self)
        twin._rng = np.random.default_rng(rng.integers(2**63))
        twin._extra = np.random.default_rng(rng.integers(2**63))
        twin._row = BLOCK_FRAMES
        for name in ("gyro_walk_bias_rad_s", "accel_walk_bias_m_s2", "gm_gyro_rad_s",
                     "gm_accel_m_s2", "vibration"):
            setattr(twin, name, list(getattr(self, name)))
        twin._gyro_matrix, twin._accel_matrix = [], []
        return twin

    def power_on_again(self, rng: np.random.Generator) -> ImuErrorModel:
        """This part switched on again on another day: the same scale factors, cross-axis
        terms, misalignment, g-sensitivity and temperature coefficients, a new turn-on bias
        (redrawn from ``rng``, as a real part's turn-on repeatability does) and its own noise,
        walk and instability from ``rng``."""
        twin = self.spare(rng)
        cfg = self.config
        twin.gyro_walk_bias_rad_s = [float(v) for v in
                                     rng.normal(0.0, cfg.gyro_bias_sigma_rad_s, 3)]
        twin.accel_walk_bias_m_s2 = [float(v) for v in
                                     rng.normal(0.0, cfg.accel_bias_sigma_m_s2, 3)]
        twin.gm_gyro_rad_s = (rng.standard_normal(3) * cfg.gyro_bias_instability_rad_s).tolist()
        twin.gm_accel_m_s2 = (rng.standard_normal(3)
                              * cfg.accel_bias_instability_m_s2).tolist()
        return twin

    # ------------------------------------------------------------------ helpers
    def _refresh_matrices(self, temperature_c: float) -> None:
        d_t = temperature_c - CALIBRATION_TEMPERATURE_C
        for scale, scale_temp, cross, attr in (
                (self.gyro_scale, self.gyro_scale_temp, self.gyro_cross, "_gyro_matrix"),
                (self.accel_scale, self.accel_scale_temp, self.accel_cross, "_accel_matrix")):
            xy, xz, yx, yz, zx, zy = cross
            sensor = [[1.0 + scale[0] + scale_temp[0] * d_t, xy, xz],
                      [yx, 1.0 + scale[1] + scale_temp[1] * d_t, yz],
                      [zx, zy, 1.0 + scale[2] + scale_temp[2] * d_t]]
            setattr(self, attr, _matmul(sensor, self._rotation))
        self._matrix_temp_c = temperature_c

    def scale_matrices(self, temperature_c: float = CALIBRATION_TEMPERATURE_C
                       ) -> tuple[list[list[float]], list[list[float]]]:
        """Gyro and accelerometer matrices (body axes in, part output out) at a temperature:
        misalignment, scale factor and cross-axis sensitivity together."""
        self._refresh_matrices(temperature_c)
        return self._gyro_matrix, self._accel_matrix

    def total_bias(self, temperature_c: float) -> tuple[list[float], list[float]]:
        """Gyro (rad/s) and accelerometer (m/s^2) bias now: turn-on, walk, instability and
        temperature terms, in the part's axes."""
        d_t = temperature_c - CALIBRATION_TEMPERATURE_C if math.isfinite(temperature_c) else 0.0
        bg = [self.gyro_walk_bias_rad_s[i] + self.gm_gyro_rad_s[i] + self.gyro_bias_temp[i] * d_t
              for i in range(3)]
        ba = [self.accel_walk_bias_m_s2[i] + self.gm_accel_m_s2[i]
              + self.accel_bias_temp[i] * d_t for i in range(3)]
        return bg, ba

    def _refill(self) -> None:
        self._block = self._rng.standard_normal((BLOCK_FRAMES, 12)).tolist()
        if self._gm_on:
            self._extra_block = self._extra.standard_normal((BLOCK_FRAMES, 6)).tolist()
        self._row = 0

    # ------------------------------------------------------------------ one sample
    def measure(self, r0: float, r1: float, r2: float, a0: float, a1: float, a2: float,
                rpm: float, temperature_c: float) -> list[float]:
        """Advance one sample; return the part's output (p, q, r rad/s, ax, ay, az m/s^2)."""
        cfg = self.config
        if self._row >= BLOCK_FRAMES:
            self._refill()
        row = self._row
        self._row = row + 1
        d = self._block[row]
        self.temperature_c = temperature_c
        sq = math.sqrt(self.dt_s)
        gw = cfg.gyro_bias_walk_rad_s_sqrt_s
        aw = cfg.accel_bias_walk_m_s2_sqrt_s
        bg = self.gyro_walk_bias_rad_s
        ba = self.accel_walk_bias_m_s2
        # the original model's arithmetic, operation for operation
        bg[0] = bg[0] + d[0] * gw * sq
        bg[1] = bg[1] + d[1] * gw * sq
        bg[2] = bg[2] + d[2] * gw * sq
        ba[0] = ba[0] + d[3] * aw * sq
        ba[1] = ba[1] + d[4] * aw * sq
        ba[2] = ba[2] + d[5] * aw * sq
        gn = cfg.gyro_noise_rad_s
        an = cfg.accel_noise_m_s2
        if self._plain:
            return [r0 + bg[0] + d[6] * gn, r1 + bg[1] + d[7] * gn, r2 + bg[2] + d[8] * gn,
                    a0 + ba[0] + d[9] * an, a1 + ba[1] + d[10] * an, a2 + ba[2] + d[11] * an]
        return self._measure_full(r0, r1, r2, a0, a1, a2, rpm, temperature_c, d, row)

    def _measure_full(self, r0: float, r1: float, r2: float, a0: float, a1: float, a2: float,
                      rpm: float, temperature_c: float, d: list[float], row: int) -> list[float]:
        cfg = self.config
        if abs(temperature_c - self._matrix_temp_c) > _MATRIX_REFRESH_C \
                or not self._gyro_matrix:
            self._refresh_matrices(temperature_c)
        d_t = temperature_c - CALIBRATION_TEMPERATURE_C
        vib = self.vibration
        if self._vib_on and rpm > 0.0:
            shaft_hz = rpm / 60.0
            theta = self.shaft_angle_rad = (self.shaft_angle_rad + 2.0 * math.pi * shaft_hz
                                            * self.dt_s) % (2.0 * math.pi)
            load = (rpm / cfg.vib_ref_rpm) ** 2
            v0 = v1 = v2 = v3 = v4 = v5 = 0.0
            for m, _rel, k, j in self._vib:
                gain = load * dlpf_gain(m * shaft_hz, cfg.dlpf_hz)
                s = math.sin(m * theta) * gain
                c = math.cos(m * theta) * gain
                v0 += k[0] * s + j[0] * c
                v1 += k[1] * s + j[1] * c
                v2 += k[2] * s + j[2] * c
                v3 += k[3] * s + j[3] * c
                v4 += k[4] * s + j[4] * c
                v5 += k[5] * s + j[5] * c
            self.vibration = vib = [v0, v1, v2, v3, v4, v5]
        elif self._vib_on:
            self.vibration = vib = [0.0] * 6
        a0 += vib[0]
        a1 += vib[1]
        a2 += vib[2]
        gm_g = self.gm_gyro_rad_s
        gm_a = self.gm_accel_m_s2
        if self._gm_on:
            e = self._extra_block[row]
            phi = self._gm_phi
            qg = self._gm_q_gyro
            qa = self._gm_q_accel
            gm_g[0] = phi * gm_g[0] + qg * e[0]
            gm_g[1] = phi * gm_g[1] + qg * e[1]
            gm_g[2] = phi * gm_g[2] + qg * e[2]
            gm_a[0] = phi * gm_a[0] + qa * e[3]
            gm_a[1] = phi * gm_a[1] + qa * e[4]
            gm_a[2] = phi * gm_a[2] + qa * e[5]
        g = self._gyro_matrix
        a = self._accel_matrix
        bg = self.gyro_walk_bias_rad_s
        ba = self.accel_walk_bias_m_s2
        tg = self.gyro_bias_temp
        ta = self.accel_bias_temp
        gn = cfg.gyro_noise_rad_s
        an = cfg.accel_noise_m_s2
        # six locals rather than a list: the slice-and-comprehension form of the clipping and
        # quantisation below cost more than the arithmetic (same operations, same order)
        o0 = (g[0][0] * r0 + g[0][1] * r1 + g[0][2] * r2 + bg[0] + gm_g[0] + tg[0] * d_t
              + vib[3] + d[6] * gn)
        o1 = (g[1][0] * r0 + g[1][1] * r1 + g[1][2] * r2 + bg[1] + gm_g[1] + tg[1] * d_t
              + vib[4] + d[7] * gn)
        o2 = (g[2][0] * r0 + g[2][1] * r1 + g[2][2] * r2 + bg[2] + gm_g[2] + tg[2] * d_t
              + vib[5] + d[8] * gn)
        o3 = (a[0][0] * a0 + a[0][1] * a1 + a[0][2] * a2 + ba[0] + gm_a[0] + ta[0] * d_t
              + d[9] * an)
        o4 = (a[1][0] * a0 + a[1][1] * a1 + a[1][2] * a2 + ba[1] + gm_a[1] + ta[1] * d_t
              + d[10] * an)
        o5 = (a[2][0] * a0 + a[2][1] * a1 + a[2][2] * a2 + ba[2] + gm_a[2] + ta[2] * d_t
              + d[11] * an)
        if self._g_sens_on:
            k0, k1, k2 = self.g_sensitivity
            o0 += k0[0] * a0 + k0[1] * a1 + k0[2] * a2
            o1 += k1[0] * a0 + k1[1] * a1 + k1[2] * a2
            o2 += k2[0] * a0 + k2[1] * a1 + k2[2] * a2
        if self._clip_on:
            gr = cfg.gyro_range_rad_s
            ar = cfg.accel_range_m_s2
            o0 = -gr if o0 < -gr else gr if o0 > gr else o0
            o1 = -gr if o1 < -gr else gr if o1 > gr else o1
            o2 = -gr if o2 < -gr else gr if o2 > gr else o2
            o3 = -ar if o3 < -ar else ar if o3 > ar else o3
            o4 = -ar if o4 < -ar else ar if o4 > ar else o4
            o5 = -ar if o5 < -ar else ar if o5 > ar else o5
        floor = math.floor
        lsb = cfg.gyro_lsb_rad_s
        if lsb:
            o0 = floor(o0 / lsb + 0.5) * lsb
            o1 = floor(o1 / lsb + 0.5) * lsb
            o2 = floor(o2 / lsb + 0.5) * lsb
        lsb = cfg.accel_lsb_m_s2
        if lsb:
            o3 = floor(o3 / lsb + 0.5) * lsb
            o4 = floor(o4 / lsb + 0.5) * lsb
            o5 = floor(o5 / lsb + 0.5) * lsb
        return [o0, o1, o2, o3, o4, o5]
