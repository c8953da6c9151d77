"""Synthetic flights and IMU/GPS recordings with known truth, for tests and benches.

Truth is built on a fine time grid (``oversample`` points per IMU period) so the simulated IMU
can report what a real one reports: the mean angular rate and the mean specific force over each
sample period (sample ``k`` covers ``(t[k-1], t[k]]``). The rate is the exact delta-angle over
the period, so integrating it with the exponential map reproduces the true attitude; errors
then come only from the simulated sensor errors, not from the generator.

Two kinds of motion:

* :func:`fixed_wing_flight`: coordinated flight from a list of segments (bank, flight-path angle,
  speed), heading rate ``g * tan(bank) / V``, so the accelerometer sees the centripetal load
  of a turn as a real one does;
* :func:`handheld_motion`: rest phases, fast rotations and translations of a sensor moved by
  hand, like the recordings used to benchmark 6-D orientation filters.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from companion.estimation.quat import (
    GRAVITY_M_S2,
    FloatArray,
    quat_conjugate,
    quat_from_euler,
    quat_from_rotvec,
    quat_multiply,
    quat_multiply_f,
    quat_normalise,
    quat_to_rotmat,
    quat_to_rotvec,
)


@dataclass(frozen=True)
class Segment:
    """One phase of a fixed-wing flight; values are reached by a smooth transition."""

    duration_s: float
    bank_deg: float = 0.0
    gamma_deg: float = 0.0
    """Flight-path angle, positive climbing."""
    speed_m_s: float = 20.0


@dataclass
class Trajectory:
    """Truth at the IMU sample times, and the ideal IMU readings."""

    t_s: FloatArray
    quat: FloatArray
    """(N, 4) body to NED."""
    pos_ned_m: FloatArray
    vel_ned_m_s: FloatArray
    gyro_rad_s: FloatArray
    """(N, 3) mean body rate over each sample period."""
    accel_m_s2: FloatArray
    """(N, 3) mean specific force over each sample period."""

    @property
    def rate_hz(self) -> float:
        return float(1.0 / (self.t_s[1] - self.t_s[0]))


@dataclass(frozen=True)
class ImuErrors:
    """Sensor error model; densities are per sqrt(Hz), biases are 1-sigma of a random draw."""

    gyro_noise_rad_s_rt_hz: float = 0.01 * np.pi / 180
    gyro_bias_rad_s: float = 0.5 * np.pi / 180
    gyro_bias_rw_rad_s_rt_s: float = 0.002 * np.pi / 180
    gyro_scale: float = 0.0
    """1-sigma of a per-axis scale-factor error (fraction)."""
    accel_noise_m_s2_rt_hz: float = 0.002
    accel_scale: float = 0.0
    """1-sigma of a per-axis accelerometer scale-factor error (fraction)."""
    accel_bias_m_s2: float = 0.05
    accel_bias_rw_m_s2_rt_s: float = 0.0005
    vibration_m_s2: float = 0.0
    """RMS of broadband structural vibration added to the accelerometer (per sample)."""
    seed: int = 0


@dataclass
class ImuRecording:
    gyro_rad_s: FloatArray
    accel_m_s2: FloatArray
    gyro_bias_rad_s: FloatArray
    """(N, 3) the true gyro bias at each sample."""
    accel_bias_m_s2: FloatArray


@dataclass
class GpsRecording:
    """GPS fixes: ``t_valid_s`` is when the fix was true, ``t_report_s`` when it arrives."""

    t_valid_s: FloatArray
    t_report_s: FloatArray
    pos_ned_m: FloatArray
    vel_ned_m_s: FloatArray
    pos_std_m: FloatArray = field(default_factory=lambda: np.zeros(3))
    vel_std_m_s: FloatArray = field(default_factory=lambda: np.zeros(3))


def _smooth_steps(t: FloatArray, starts: FloatArray, values: FloatArray, ramp_s: float) -> FloatArray:
    """Piecewise-constant profile with raised-cosine transitions of ``ramp_s`` at each change."""
    out = np.full_like(t, values[0])
    for start, before, after in zip(starts[1:], values[:-1], values[1:], strict=True):
        x = np.clip((t - start) / ramp_s, 0.0, 1.0)
        out += (after - before) * 0.5 * (1.0 - np.cos(np.pi * x))
    return out


def _from_fine(
    t_fine: FloatArray,
    q_fine: FloatArray,
    pos_fine: FloatArray,
    vel_fine: FloatArray,
    acc_fine: FloatArray,
    oversample: int,
) -> Trajectory:
    """Decimate a fine-grid truth to IMU samples and compute the period-mean IMU readings."""
    dt_fine = t_fine[1] - t_fine[0]
    g_ned = np.array([0.0, 0.0, GRAVITY_M_S2])
    rot = quat_to_rotmat(q_fine)
    f_body = np.einsum("nji,nj->ni", rot, acc_fine - g_ned)
    idx = np.arange(0, len(t_fine), oversample)
    q = q_fine[idx]
    dt = dt_fine * oversample
    gyro = np.empty((len(idx), 3))
    accel = np.empty((len(idx), 3))
    rel = quat_multiply(quat_conjugate(q[:-1]), q[1:])
    gyro[1:] = quat_to_rotvec(rel) / dt
    # trapezoid mean of the fine specific force over each period
    cum = np.concatenate(([np.zeros(3)], np.cumsum(0.5 * (f_body[1:] + f_body[:-1]) * dt_fine, 0)))
    accel[1:] = (cum[idx[1:]] - cum[idx[:-1]]) / dt
    fine_rate = quat_to_rotvec(quat_multiply(quat_conjugate(q_fine[0]), q_fine[1])) / dt_fine
    gyro[0] = fine_rate
    accel[0] = f_body[0]
    return Trajectory(
        t_s=t_fine[idx] - t_fine[0],
        quat=quat_normalise(q),
        pos_ned_m=pos_fine[idx],
        vel_ned_m_s=vel_fine[idx],
        gyro_rad_s=gyro,
        accel_m_s2=accel,
    )


def fixed_wing_flight(
    segments: list[Segment],
    rate_hz: float = 100.0,
    alpha_deg: float = 2.0,
    heading0_rad: float = 0.0,
    ramp_s: float = 2.0,
    oversample: int = 10,
) -> Trajectory:
    """Coordinated flight through ``segments``; the aircraft holds ``alpha_deg`` angle of attack.

    The first segment's values hold from t=0 (no transition), so a single-segment flight is a
    steady state from the first sample.
    """
    if not segments:
        raise ValueError("fixed_wing_flight needs at least one segment")
    durations = np.array([s.duration_s for s in segments])
    starts = np.concatenate(([0.0], np.cumsum(durations)[:-1]))
    total = float(durations.sum())
    n_fine = int(round(total * rate_hz * oversample)) + 1
    t = np.arange(n_fine) / (rate_hz * oversample)
    bank = np.radians(_smooth_steps(t, starts, np.array([s.bank_deg for s in segments]), ramp_s))
    gamma = np.radians(_smooth_steps(t, starts, np.array([s.gamma_deg for s in segments]), ramp_s))
    speed = _smooth_steps(t, starts, np.array([s.speed_m_s for s in segments]), ramp_s)
    dt = t[1] - t[0]
    yaw_rate = GRAVITY_M_S2 * np.tan(bank) * np.cos(gamma) / speed
    heading = heading0_rad + np.concatenate(([0.0], np.cumsum(0.5 * (yaw_rate[1:] + yaw_rate[:-1]) * dt)))
    vel = np.stack(
        (
            speed * np.cos(gamma) * np.cos(heading),
            speed * np.cos(gamma) * np.sin(heading),
            -speed * np.sin(gamma),
        ),
        axis=-1,
    )
    pos = np.concatenate(([np.zeros(3)], np.cumsum(0.5 * (vel[1:] + vel[:-1]) * dt, axis=0)))
    acc = np.asarray(np.gradient(vel, dt, axis=0, edge_order=2), dtype=float)
    # Attitude: body x along the velocity pitched up by alpha in the body's own frame, rolled by
    # the bank angle about the velocity vector (so lift, and the accelerometer, stay in the
    # symmetry plane).
    q_path = quat_from_euler(np.zeros_like(t), gamma, heading)
    q_bank = quat_from_euler(bank, np.zeros_like(t), np.zeros_like(t))
    q_alpha = quat_from_euler(np.zeros_like(t), np.full_like(t, np.radians(alpha_deg)), 0.0 * t)
    q = quat_multiply(quat_multiply(q_path, q_bank), q_alpha)
    return _from_fine(t, q, pos, vel, acc, oversample)


def handheld_motion(
    duration_s: float = 120.0,
    rate_hz: float = 100.0,
    seed: int = 0,
    rest_fraction: float = 0.25,
    max_rate_rad_s: float = 6.0,
    max_accel_m_s2: float = 6.0,
    oversample: int = 10,
) -> Trajectory:
    """Random hand-held motion: rest, rotation-only, translation-only and combined phases.

    Phases last 5-15 s; each has random smooth angular-rate and position profiles (sums of
    sinusoids) whose envelope vanishes at phase edges, so the motion is continuous.
    """
    rng = np.random.default_rng(seed)
    n_fine = int(round(duration_s * rate_hz * oversample)) + 1
    t = np.arange(n_fine) / (rate_hz * oversample)
    dt = t[1] - t[0]
    omega_b = np.zeros((n_fine, 3))
    pos = np.zeros((n_fine, 3))
    start = 0.0
    first = True
    while start < duration_s:
        length = float(rng.uniform(5.0, 15.0))
        end = min(start + length, duration_s)
        kind = "rest" if first or rng.random() < rest_fraction else str(
            rng.choice(["rotation", "translation", "combined"])
        )
        first = False
        mask = (t >= start) & (t < end)
        tau = (t[mask] - start) / max(end - start, 1e-9)
        envelope = np.sin(np.pi * tau) ** 2
        if kind in ("rotation", "combined"):
            intensity = rng.uniform(0.2, 1.0) * max_rate_rad_s
            for axis in range(3):
                for _ in range(3):
                    freq = rng.uniform(0.1, 1.5)
                    amp = intensity / 3.0 * rng.uniform(0.3, 1.0)
                    omega_b[mask, axis] += envelope * amp * np.sin(
                        2 * np.pi * freq * t[mask] + rng.uniform(0, 2 * np.pi)
                    )
        if kind in ("translation", "combined"):
            intensity = rng.uniform(0.3, 1.0) * max_accel_m_s2
            for axis in range(3):
                for _ in range(2):
                    freq = rng.uniform(0.3, 1.5)
                    amp = intensity / 2.0 / (2 * np.pi * freq) ** 2 * rng.uniform(0.3, 1.0)
                    pos[mask, axis] += envelope * amp * np.sin(
                        2 * np.pi * freq * t[mask] + rng.uniform(0, 2 * np.pi)
                    )
        start = end
    # integrate the body rate with the exponential map on the fine grid
    q = np.empty((n_fine, 4))
    q0 = quat_from_euler(rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(-np.pi, np.pi))
    cur = tuple(float(c) for c in q0)
    q[0] = cur
    steps = quat_from_rotvec(0.5 * (omega_b[1:] + omega_b[:-1]) * dt).tolist()
    for k in range(1, n_fine):
        cur = quat_multiply_f(*cur, *steps[k - 1])
        q[k] = cur
    vel = np.asarray(np.gradient(pos, dt, axis=0, edge_order=2), dtype=float)
    acc = np.asarray(np.gradient(vel, dt, axis=0, edge_order=2), dtype=float)
    return _from_fine(t, quat_normalise(q), pos, vel, acc, oversample)


def add_imu_errors(traj: Trajectory, errors: ImuErrors) -> ImuRecording:
    """Corrupt ideal IMU readings with biases, bias random walk, white noise and vibration."""
    rng = np.random.default_rng(errors.seed)
    n = len(traj.t_s)
    rate = traj.rate_hz
    dt = 1.0 / rate
    gyro_bias = rng.normal(0.0, errors.gyro_bias_rad_s, 3) + np.cumsum(
        rng.normal(0.0, errors.gyro_bias_rw_rad_s_rt_s * np.sqrt(dt), (n, 3)), axis=0
    )
    accel_bias = rng.normal(0.0, errors.accel_bias_m_s2, 3) + np.cumsum(
        rng.normal(0.0, errors.accel_bias_rw_m_s2_rt_s * np.sqrt(dt), (n, 3)), axis=0
    )
    scale = 1.0 + rng.normal(0.0, errors.gyro_scale, 3)
    gyro = (
        traj.gyro_rad_s * scale
        + gyro_bias
        + rng.normal(0.0, errors.gyro_noise_rad_s_rt_hz * np.sqrt(rate), (n, 3))
    )
    accel_scale = 1.0 + rng.normal(0.0, errors.accel_scale, 3)
    accel = (
        traj.accel_m_s2 * accel_scale
        + accel_bias
        + rng.normal(0.0, errors.accel_noise_m_s2_rt_hz * np.sqrt(rate), (n, 3))
        + rng.normal(0.0, errors.vibration_m_s2, (n, 3))
    )
    return ImuRecording(gyro, accel, gyro_bias, accel_bias)


def gps_fixes(
    traj: Trajectory,
    rate_hz: float = 10.0,
    pos_std_m: tuple[float, float, float] = (1.0, 1.0, 2.0),
    vel_std_m_s: tuple[float, float, float] = (0.1, 0.1, 0.2),
    latency_s: float = 0.0,
    seed: int = 1,
) -> GpsRecording:
    """White-noise GPS fixes at ``rate_hz``, each reported ``latency_s`` after it was valid."""
    rng = np.random.default_rng(seed)
    step = max(1, int(round(traj.rate_hz / rate_hz)))
    idx = np.arange(0, len(traj.t_s), step)
    p_std = np.asarray(pos_std_m, dtype=float)
    v_std = np.asarray(vel_std_m_s, dtype=float)
    return GpsRecording(
        t_valid_s=traj.t_s[idx],
        t_report_s=traj.t_s[idx] + latency_s,
        pos_ned_m=traj.pos_ned_m[idx] + rng.normal(0.0, 1.0, (len(idx), 3)) * p_std,
        vel_ned_m_s=traj.vel_ned_m_s[idx] + rng.normal(0.0, 1.0, (len(idx), 3)) * v_std,
        pos_std_m=p_std,
        vel_std_m_s=v_std,
    )
