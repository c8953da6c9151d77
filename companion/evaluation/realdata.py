"""IMU-only attitude filters on real recordings: loaders, alignment, error and scoring.

Two kinds of real data are committed in ``tests/data`` (see its README):

* ``imu-truth/leiria/``: four MEMS IMUs and an XSENS MTi-30 on an ABB industrial robot arm,
  with the robot's own tool orientation as truth (Leiria data set, MIT licence). One ``.npz``
  per recording, named ``<speed>_path<k>_<device>.npz``;
* ``px4-ulog/sample.ulg``: a real PX4 multicopter flight. It has no truth: PX4's EKF2
  attitude is a reference, so a comparison with it measures *agreement with EKF2*, not
  accuracy.

Why the comparison is built the way it is:

* **Same samples for every filter.** The Leiria time stamps are the PC's arrival times, about
  100-115 Hz and jittered (0.002 to 0.02 s between samples). VQF takes one fixed sample period,
  so every filter is fed the same recording resampled onto a uniform grid
  (:func:`resample_uniform`): rates and specific forces are integrated over the irregular
  periods and differenced on the grid, which keeps the integrated rotation (and the clipping)
  of the original samples. Our filter can also run on the raw irregular samples with their
  time stamps (``estimate_attitude(..., t_s=...)``); that figure is reported beside, not
  instead.
* **Same truth for every filter.** The mounting of each IMU on the robot's tool is unknown.
  It is estimated once per recording from the raw gyro and the truth only, never from a
  filter's output (:func:`fit_alignment`), so no filter gets a mounting tuned to its own
  errors: the rotation increments seen by the gyro over short windows are the robot's tool
  increments seen through the mounting, which is Wahba's problem (solved by SVD). The robot's
  reports reach the PC later than the motion they describe; one delay for the acquisition
  (:data:`TRUTH_LAG_S`, from per-recording estimates) is applied to the truth. The vertical in the robot's base frame is the base's z axis (:data:`ROBOT_UP_BASE`). That
  was checked with the accelerometers, again without any filter: over a recording that starts
  and ends at rest the mean of the specific force rotated into the base frame is gravity (the
  motion's accelerations integrate to the velocity change, zero). Per recording that estimate
  scatters by about 1 degree (accelerometer biases), its mean over all 77 recordings is 0.12
  degrees from the base's z axis; one vertical for the one robot is the better truth.
* **Scored where the truth holds**: from the end of the robot's start-up glitches
  (:func:`truth_valid_from_s`, :func:`consistent_from_s`); every filter runs from sample 0.
* **A split fixed before tuning**: :data:`HELD_OUT_SPEEDS` and :data:`HELD_OUT_DEVICES`.
* **Heading is ignored**: inclination error is the angle between the vertical as the filter
  sees it in the sensor frame and the true vertical in the sensor frame, so a 6-D filter's
  free heading and the robot base's heading do not enter.

Scoring the filters on these recordings is :mod:`companion.evaluation.realdata_scoring`; the
filters themselves are :mod:`companion.estimation.imu_filters`'s, as in the SITL evaluation.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from companion.estimation.quat import (
    FloatArray,
    quat_conjugate,
    quat_multiply,
    quat_to_rotmat,
    quat_to_rotvec,
)

REPO_ROOT = Path(__file__).resolve().parents[2]
LEIRIA_DIR = REPO_ROOT / "tests" / "data" / "imu-truth" / "leiria"
PX4_ULOG = REPO_ROOT / "tests" / "data" / "px4-ulog" / "sample.ulg"

RESAMPLE_RATE_HZ = 100.0
"""The uniform rate every filter is fed (the Leiria IMUs were set to sample at 100 Hz)."""
CLIP_RAD_S = math.radians(440.0)
"""Rates at or above this are taken as clipped (the MPU gyros saturate near 450 deg/s)."""

LEIRIA_DEVICES = ("LSM9DS0", "MPU9150", "MPU6500RM3100", "MPU6050RM3100")
LEIRIA_SPEEDS = ("V_300", "V_500", "V_800", "V1000", "V1500", "eV50p")

# Chosen before any tuning: the filter may be tuned on TUNING sequences only; the HELD_OUT
# sequences (the two fastest speeds for every device, and one device at every speed) were only
# ever scored, never used to choose anything.
HELD_OUT_SPEEDS = ("V1000", "V1500")
HELD_OUT_DEVICES = ("MPU6500RM3100",)

TRUTH_LAG_S = -0.080
"""The robot's reports reach the PC this much after the motion they describe (truth read at
``t + TRUTH_LAG_S``). One figure for the acquisition: the median of the per-recording estimates
(``fit_alignment(rec, lag_s=None)``) over all 77 recordings, quartiles -85 and -76 ms. A
per-recording estimate wanders on the slow recordings (the fit hardly depends on the lag when
the arm turns slowly: 5 % of them come out below -140 or above -60 ms), and a lag 20 ms off
costs 5 degrees at 300 deg/s, so the one acquisition figure is the better truth."""

ROBOT_UP_BASE = np.array((0.0, 0.0, 1.0))
"""The vertical (up) in the robot's base frame (see the module docstring)."""

_NAME = re.compile(r"^(?P<speed>[A-Za-z0-9_]+?)_path(?P<path>\d)_(?P<device>[A-Za-z0-9]+)$")


@dataclass(frozen=True)
class ImuRecording:
    """One real IMU recording in SI units, body axes of the sensor.

    ``truth_wxyz`` is the robot's tool orientation (its frame, not NED; see
    :func:`fit_alignment`) or None; ``reference_wxyz`` is another estimator's attitude on the
    same samples (PX4 EKF2: body FRD to NED), or None.
    """

    name: str
    t_s: FloatArray
    gyro_rad_s: FloatArray
    accel_m_s2: FloatArray
    truth_wxyz: FloatArray | None = None
    reference_wxyz: FloatArray | None = None
    score_from_s: float = 0.0
    """Errors are scored from this time after the first sample on (the truth's valid part)."""

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0])

    @property
    def speed(self) -> str:
        m = _NAME.match(self.name)
        return m.group("speed") if m else ""

    @property
    def device(self) -> str:
        m = _NAME.match(self.name)
        return m.group("device") if m else ""

    @property
    def held_out(self) -> bool:
        """True for the sequences kept out of every tuning decision."""
        return is_held_out(self.name)


def is_held_out(name: str) -> bool:
    """True for a Leiria recording name kept out of every tuning decision (see the split)."""
    m = _NAME.match(name)
    if m is None:
        return False
    return m.group("speed") in HELD_OUT_SPEEDS or m.group("device") in HELD_OUT_DEVICES


# ---------------------------------------------------------------------------------------------
# loading


def repair_time(t_s: ArrayLike) -> FloatArray:
    """Time stamps made strictly increasing: isolated out-of-order stamps are interpolated.

    The Leiria PC clock occasionally records a stray stamp (e.g. 0 s in the middle of a
    recording); a sample whose stamp is not between its neighbours' gets the mean of theirs.
    Remaining non-increasing stamps (duplicates) are spread evenly to the next larger one.
    """
    t = np.asarray(t_s, dtype=float).copy()
    n = len(t)
    if n < 3:
        return t
    bad = np.zeros(n, dtype=bool)
    inner = ~((t[:-2] < t[1:-1]) & (t[1:-1] < t[2:])) & (t[:-2] < t[2:])
    bad[1:-1] = inner
    if bad.any():
        good = ~bad
        t[bad] = np.interp(np.flatnonzero(bad), np.flatnonzero(good), t[good])
    for k in range(1, n):
        if t[k] <= t[k - 1]:
            t[k] = t[k - 1] + 1e-6
    return t


def _finite_rows(*arrays: FloatArray) -> np.ndarray:
    keep = np.ones(len(arrays[0]), dtype=bool)
    for a in arrays:
        keep &= np.isfinite(a.reshape(len(a), -1)).all(axis=1)
    return keep


def list_leiria(root: Path = LEIRIA_DIR) -> list[str]:
    """Names of the raw-IMU recordings of the subset, sorted (XSENS files are separate)."""
    names = [p.stem for p in root.glob("*.npz") if not p.stem.endswith("_XSENS")]
    return sorted(names)


def _truth_from_reports(
    t_s: FloatArray, truth: FloatArray, report_index: np.ndarray, keep: np.ndarray
) -> FloatArray:
    """The robot's orientation re-interpolated from its reports only (see the converter).

    Between reports the source interpolated quaternion components linearly without minding
    their sign, which invents a half turn whenever two reports have opposite signs; here each
    report is taken as reported at the sample it arrived with, and the samples between are
    normalised linear interpolations with continuous signs. (The robot's own report stamps,
    ``ABBtime``, were tried instead of the arrival times: their pairing with the arrivals slips
    within some recordings, and where it holds the scores do not change.)
    """
    kept_index = np.cumsum(keep) - 1
    idx = report_index[keep[report_index]]
    q = truth[idx]
    good = np.isfinite(q).all(axis=1) & (np.linalg.norm(q, axis=1) > 0.5)
    idx = idx[good]
    # ABB reports the quaternion of the base seen from the tool; its conjugate maps tool-frame
    # vectors into the base frame (the convention of every attitude here). Checked on the data:
    # only this way round do the gyro's rotation increments match the robot's (1-2 degrees
    # against 20-45 for the other readings).
    return quat_conjugate(interpolate_quat(t_s[kept_index[idx]], q[good], t_s))


def truth_valid_from_s(rec: ImuRecording, search_fraction: float = 0.3) -> float:
    """When the truth starts to describe the sensor: after the robot's stale first reports.

    The first robot reports of some recordings jump by tens of degrees while the IMU's gyro
    sees no motion at all (the robot's report stream starting up). The truth is trusted from the
    end of the last such jump in the first ``search_fraction`` of the recording: a 0.1 s step
    in which the truth turns more than 5 degrees while the gyro integrates less than 1.
    """
    truth = truth_wxyz(rec)
    u = resample_uniform(rec, 100.0)
    q = interpolate_quat(rec.t_s, truth, u.t_s)
    start = 0.0
    n_search = int(len(q) * search_fraction)
    for k in range(0, n_search, 10):
        k1 = min(k + 10, len(q) - 1)
        turn = float(np.linalg.norm(quat_to_rotvec(quat_multiply(quat_conjugate(q[k]), q[k1]))))
        gyro_turn = float(np.linalg.norm(u.gyro_rad_s[k + 1: k1 + 1].sum(axis=0) * 0.01))
        if turn > math.radians(5.0) and gyro_turn < math.radians(1.0):
            start = float(u.t_s[k1] - u.t_s[0]) + 0.2
    return start


def load_leiria(name: str, root: Path = LEIRIA_DIR) -> ImuRecording:
    """One raw-IMU recording of the subset: placeholder rows dropped, time stamps repaired,
    truth re-interpolated from the robot's reports, ``score_from_s`` set by
    :func:`truth_valid_from_s`."""
    with np.load(root / f"{name}.npz") as z:
        t = np.asarray(z["t_s"], dtype=float)
        gyro = np.asarray(z["gyro_rad_s"], dtype=float)
        accel = np.asarray(z["accel_m_s2"], dtype=float)
        truth = np.asarray(z["truth_wxyz"], dtype=float)
        reports = np.asarray(z["truth_report_index"], dtype=np.int64)
    # the acquisition's first row is a placeholder (NaN or exact zeros): no real accelerometer
    # reads exactly zero on all three axes
    keep = _finite_rows(t.reshape(-1, 1), gyro, accel) & (np.abs(accel).sum(axis=1) > 0.0)
    t_kept = repair_time(t[keep])
    q = _truth_from_reports(t_kept, truth, reports, keep)
    rec = ImuRecording(name, t_kept, gyro[keep], accel[keep], q)
    return replace(rec, score_from_s=truth_valid_from_s(rec))


def load_leiria_xsens(speed: str, path: int, root: Path = LEIRIA_DIR) -> ImuRecording | None:
    """The XSENS MTi-30's own orientation (``reference_wxyz``) and the truth on its samples.

    The truth is rebuilt from the robot's reports as in :func:`load_leiria`; there are no raw
    samples (``gyro_rad_s`` and ``accel_m_s2`` are zeros).
    """
    f = root / f"{speed}_path{path}_XSENS.npz"
    if not f.is_file():
        return None
    with np.load(f) as z:
        t = np.asarray(z["t_s"], dtype=float)
        ref = np.asarray(z["xsens_wxyz"], dtype=float)
        truth = np.asarray(z["truth_wxyz"], dtype=float)
        reports = np.asarray(z["truth_report_index"], dtype=np.int64)
    keep = _finite_rows(t.reshape(-1, 1), ref) & (np.linalg.norm(ref, axis=1) > 0.5)
    t_kept = repair_time(t[keep])
    q = _truth_from_reports(t_kept, truth, reports, keep)
    empty = np.zeros((len(t_kept), 3))
    # like ABB's, the XSENS quaternion is the navigation frame seen from the sensor: its
    # conjugate maps sensor vectors into the (z-up) navigation frame. Read the other way its
    # vertical disagrees with the robot's by 40-60 degrees on the combined-rotation paths.
    return ImuRecording(f"{speed}_path{path}_XSENS", t_kept, empty, empty, q,
                        quat_conjugate(ref[keep]))


def load_px4_ulog(path: Path = PX4_ULOG) -> ImuRecording:
    """``sensor_combined`` (FRD body, rad/s and m/s^2) with EKF2's attitude held onto it.

    The integrated rates and specific forces of ``sensor_combined`` are divided by their own
    integration intervals, so sample ``k`` is the mean over the period ending at its time stamp,
    the convention of :mod:`companion.estimation.attitude`. EKF2's ``vehicle_attitude`` (body
    FRD to NED, about 94 Hz) is interpolated onto the sensor time stamps.
    """
    from pyulog import ULog

    ulog = ULog(str(path), ["sensor_combined", "vehicle_attitude"])
    sc = ulog.get_dataset("sensor_combined").data
    va = ulog.get_dataset("vehicle_attitude").data
    t = np.asarray(sc["timestamp"], dtype=float) * 1e-6
    gyro = np.column_stack([np.asarray(sc[f"gyro_rad[{i}]"], dtype=float) for i in range(3)])
    accel = np.column_stack(
        [np.asarray(sc[f"accelerometer_m_s2[{i}]"], dtype=float) for i in range(3)]
    )
    tq = np.asarray(va["timestamp"], dtype=float) * 1e-6
    q = np.column_stack([np.asarray(va[f"q[{i}]"], dtype=float) for i in range(4)])
    ref = interpolate_quat(tq, q, t)
    keep = _finite_rows(t.reshape(-1, 1), gyro, accel, ref) & (t >= tq[0]) & (t <= tq[-1])
    return ImuRecording("px4_sample", repair_time(t[keep]), gyro[keep], accel[keep], None,
                        ref[keep])


# ---------------------------------------------------------------------------------------------
# resampling


def interpolate_quat(t_src: FloatArray, q_src: FloatArray, t_dst: FloatArray) -> FloatArray:
    """Normalised linear interpolation (nlerp) of a quaternion series, signs made continuous."""
    q = np.array(q_src, dtype=float)
    flips = np.cumprod(np.where(np.sum(q[1:] * q[:-1], axis=1) < 0.0, -1.0, 1.0))
    q[1:] *= flips[:, None]
    out = np.column_stack([np.interp(t_dst, t_src, q[:, i]) for i in range(4)])
    return out / np.linalg.norm(out, axis=1, keepdims=True)  # type: ignore[no-any-return]


def _period_means_on_grid(t_s: FloatArray, x: FloatArray, grid_s: FloatArray) -> FloatArray:
    """Sample ``k`` of ``x`` is the mean over ``(t[k-1], t[k]]``: integrate, then difference."""
    dt = np.diff(t_s)
    cum = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(x[1:] * dt[:, None], axis=0)])
    at = np.column_stack([np.interp(grid_s, t_s, cum[:, i]) for i in range(x.shape[1])])
    step = np.diff(grid_s)
    return np.vstack([x[:1], np.diff(at, axis=0) / step[:, None]])  # type: ignore[no-any-return]


def resample_uniform(rec: ImuRecording, rate_hz: float = RESAMPLE_RATE_HZ) -> ImuRecording:
    """The recording on a uniform grid, keeping each signal's integral (see module docstring)."""
    grid = rec.t_s[0] + np.arange(int(rec.duration_s * rate_hz) + 1) / rate_hz
    gyro = _period_means_on_grid(rec.t_s, rec.gyro_rad_s, grid)
    accel = _period_means_on_grid(rec.t_s, rec.accel_m_s2, grid)
    truth = None if rec.truth_wxyz is None else interpolate_quat(rec.t_s, rec.truth_wxyz, grid)
    ref = (
        None if rec.reference_wxyz is None
        else interpolate_quat(rec.t_s, rec.reference_wxyz, grid)
    )
    return replace(rec, t_s=grid, gyro_rad_s=gyro, accel_m_s2=accel, truth_wxyz=truth,
                   reference_wxyz=ref)


# ---------------------------------------------------------------------------------------------
# alignment


@dataclass(frozen=True)
class Alignment:
    """What ties a sensor's vertical to the robot's tool orientation.

    ``mount`` maps sensor-frame vectors into the tool frame; ``up_base`` is the unit vertical
    (up) in the robot's base frame; ``lag_s`` is how much later the truth's clock sees the same
    motion (the truth is read at ``t + lag_s``); ``accel_up_base`` is the vertical the
    accelerometer alone suggests for this recording (a check on ``up_base``).
    """

    mount: FloatArray
    up_base: FloatArray
    lag_s: float
    accel_up_base: FloatArray
    residual_rad: float
    """Median angle between gyro and truth rotation increments after the fit (a check)."""


def _angular_speed(t_s: FloatArray, q: FloatArray) -> FloatArray:
    rel = quat_multiply(quat_conjugate(q[:-1]), q[1:])
    ang = np.linalg.norm(quat_to_rotvec(rel), axis=1) / np.diff(t_s)
    return np.concatenate([ang[:1], ang])


def _smooth(x: FloatArray, n: int) -> FloatArray:
    kernel = np.ones(n) / n
    return np.convolve(x, kernel, mode="same")


def estimate_lag_s(rec: ImuRecording, max_lag_s: float = 0.3) -> float:
    """Clock offset truth vs sensor: the lag that best matches gyro and truth rotation speeds.

    Both speeds are smoothed over 0.3 s (the truth is reported at about 15 Hz); the lag is
    searched on a 10 ms grid, refined by a parabola through the best three.
    """
    if rec.truth_wxyz is None:
        raise ValueError("estimate_lag_s: the recording has no truth")
    u = resample_uniform(rec, 100.0)
    assert u.truth_wxyz is not None
    w_gyro = _smooth(np.linalg.norm(u.gyro_rad_s, axis=1), 30)
    w_truth = _smooth(_angular_speed(u.t_s, u.truth_wxyz), 30)
    lags = np.arange(-int(max_lag_s * 100), int(max_lag_s * 100) + 1)
    cost = np.empty(len(lags))
    n = len(w_gyro)
    for i, lag_np in enumerate(lags):
        lag = int(lag_np)
        a = w_gyro[max(0, -lag): n - max(0, lag)]
        b = w_truth[max(0, lag): n - max(0, -lag)]
        cost[i] = float(np.mean((a - b) ** 2))
    i = int(np.argmin(cost))
    frac = 0.0
    if 0 < i < len(lags) - 1:
        den = cost[i - 1] - 2 * cost[i] + cost[i + 1]
        frac = 0.5 * (cost[i - 1] - cost[i + 1]) / den if den > 0 else 0.0
    return float((lags[i] + frac) / 100.0)


def wahba(a: FloatArray, b: FloatArray, w: FloatArray) -> FloatArray:
    """Rotation R minimising sum w |a_i - R b_i|^2 (SVD solution of Wahba's problem)."""
    m = (a * w[:, None]).T @ b
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag((1.0, 1.0, d)) @ vt  # type: ignore[no-any-return]


def fit_alignment(
    rec: ImuRecording,
    window_s: float = 0.5,
    up_base: ArrayLike = ROBOT_UP_BASE,
    lag_s: float | None = TRUTH_LAG_S,
) -> Alignment:
    """Mounting, base vertical and clock lag from the raw gyro, accelerometer and truth.

    No filter output enters, so every filter is scored against the same truth. Steps:

    1. the lag: ``lag_s`` (:data:`TRUTH_LAG_S` by default, the acquisition's), or with
       ``lag_s=None`` estimated for this recording: a first guess from the rotation speeds
       (:func:`estimate_lag_s`), refined in 5 ms steps over +-80 ms to the lag at which the
       mounting fit of step 2 leaves the smallest residual;
    2. the mounting: over half-overlapping ``window_s`` windows the gyro's integrated rotation
       (sensor frame) and the truth's relative rotation (tool frame) are the same rotation seen
       in two frames, so their rotation vectors satisfy ``r_tool = mount @ r_sensor``; windows
       that turned at least 3 degrees and held no clipped rate are weighted equally in Wahba's
       problem (a gyro bias of 0.01 rad/s moves a 0.5 s increment by 0.3 degrees at most);
    3. the vertical is ``up_base`` (the robot base's z axis by default); the mean of
       ``truth @ mount @ accel`` over the recording (it starts and ends at rest, so the
       motion's accelerations average to the velocity change: zero) is returned beside it as
       ``accel_up_base`` for checking.
    """
    if rec.truth_wxyz is None:
        raise ValueError("fit_alignment: the recording has no truth")
    u = resample_uniform(rec, 100.0)
    truth_u = truth_wxyz(u)
    step = max(1, int(round(window_s * 100.0)))
    gyro = u.gyro_rad_s
    clipped: np.ndarray = np.asarray((np.abs(gyro) >= CLIP_RAD_S).any(axis=1))
    start = int(rec.score_from_s * 100.0)
    starts = np.arange(start, len(gyro) - step, max(1, step // 2))
    r_sensor = np.empty((len(starts), 3))
    usable = np.ones(len(starts), dtype=bool)
    for i, k0 in enumerate(starts):
        q = np.array((1.0, 0.0, 0.0, 0.0))
        for k in range(k0 + 1, k0 + step + 1):
            q = quat_multiply(q, _rotvec_to_quat(gyro[k] * 0.01))
        r_sensor[i] = quat_to_rotvec(q)
        usable[i] = not clipped[k0 + 1: k0 + step + 1].any()

    def fit(lag_s: float) -> tuple[float, FloatArray, float]:
        q0 = interpolate_quat(u.t_s, truth_u, u.t_s[starts] + lag_s)
        q1 = interpolate_quat(u.t_s, truth_u, u.t_s[starts + step] + lag_s)
        r_tool = quat_to_rotvec(quat_multiply(quat_conjugate(q0), q1))
        use = usable & (np.linalg.norm(r_tool, axis=1) >= math.radians(3.0))
        if use.sum() < 3:
            raise ValueError(f"fit_alignment: {rec.name} does not rotate enough to find the mounting")
        a, b = r_tool[use], r_sensor[use]
        weight = np.ones(len(a))
        for _ in range(5):
            # robust: windows far off the fit (a truth hiccup, a clock jump) are left out
            mount = wahba(a, b, weight)
            resid = np.linalg.norm(a - b @ mount.T, axis=1)
            weight = (resid <= max(3.0 * float(np.median(resid)), math.radians(2.0))).astype(float)
        kept = resid[weight > 0]
        return float(np.mean(kept**2)), mount, float(np.median(resid))

    if lag_s is None:
        coarse = estimate_lag_s(rec)
        candidates = coarse + np.arange(-0.08, 0.0801, 0.005)
        costs = [fit(float(lag))[0] for lag in candidates]
        lag = float(candidates[int(np.argmin(costs))])
    else:
        lag = float(lag_s)
    _, mount, residual = fit(lag)
    truth = interpolate_quat(u.t_s, truth_u, u.t_s + lag)
    rot = quat_to_rotmat(truth)
    f_base = np.einsum("nij,jk,nk->ni", rot, mount, u.accel_m_s2)
    up = f_base[1:].mean(axis=0)
    vertical = np.asarray(up_base, dtype=float)
    return Alignment(mount, vertical / np.linalg.norm(vertical), lag,
                     up / np.linalg.norm(up), residual)


def truth_wxyz(rec: ImuRecording) -> FloatArray:
    """The recording's truth quaternions (ValueError if it has none)."""
    if rec.truth_wxyz is None:
        raise ValueError(f"{rec.name} has no truth")
    return rec.truth_wxyz


def _rotvec_to_quat(v: FloatArray) -> FloatArray:
    angle = float(np.linalg.norm(v))
    if angle < 1e-12:
        return np.array((1.0, 0.5 * v[0], 0.5 * v[1], 0.5 * v[2]))
    s = math.sin(0.5 * angle) / angle
    return np.array((math.cos(0.5 * angle), s * v[0], s * v[1], s * v[2]))


def consistent_from_s(
    rec: ImuRecording,
    align: Alignment,
    window_s: float = 0.5,
    max_disagreement_rad: float = math.radians(8.0),
    search_fraction: float = 0.3,
) -> float:
    """When the truth and the gyro start to agree: the end of the start-up glitches.

    In the first seconds of some recordings the robot's reported rotation disagrees with the
    gyro's by 10-120 degrees over half a second while the rest of the recording agrees within
    1-3 degrees (median): the report stream starting up, not the sensor. Over overlapping
    ``window_s`` windows the gyro's rotation (mapped through the mounting) is compared with the
    truth's; scoring starts after the last window of the first ``search_fraction`` of the
    recording that disagrees by more than ``max_disagreement_rad``. No filter output enters.
    """
    truth = interpolate_quat(rec.t_s, truth_wxyz(rec), rec.t_s + align.lag_s)
    u = resample_uniform(replace(rec, truth_wxyz=truth), 100.0)
    q_truth = truth_wxyz(u)
    step = max(1, int(round(window_s * 100.0)))
    start = rec.score_from_s
    stop = int(len(u.t_s) * search_fraction)
    for k0 in range(0, max(0, stop - step), step // 2):
        k1 = k0 + step
        q = np.array((1.0, 0.0, 0.0, 0.0))
        for k in range(k0 + 1, k1 + 1):
            q = quat_multiply(q, _rotvec_to_quat(u.gyro_rad_s[k] * 0.01))
        rel_sensor = align.mount @ quat_to_rotmat(q) @ align.mount.T
        rel_truth = quat_to_rotmat(quat_multiply(quat_conjugate(q_truth[k0]), q_truth[k1]))
        diff = rel_sensor @ rel_truth.T
        angle = math.acos(max(-1.0, min(1.0, (float(np.trace(diff)) - 1.0) / 2.0)))
        if angle > max_disagreement_rad:
            start = max(start, float(u.t_s[k1] - u.t_s[0]))
    return start


def true_up_sensor(rec: ImuRecording, align: Alignment) -> FloatArray:
    """The true vertical (up, unit) in the sensor frame at each sample of ``rec``."""
    truth = interpolate_quat(rec.t_s, truth_wxyz(rec), rec.t_s + align.lag_s)
    rot = quat_to_rotmat(truth)
    # up_sensor = mount^T @ truth^T @ up_base
    up_tool = np.einsum("nji,j->ni", rot, align.up_base)
    return up_tool @ align.mount  # type: ignore[no-any-return]


def up_sensor_from_quat(q_wxyz: ArrayLike, frame: str) -> FloatArray:
    """The vertical (up, unit) in the sensor frame from a body-to-navigation attitude.

    ``frame`` is ``"ned"`` (our filter, PX4) or ``"enu"`` (VQF, Madgwick, z up).
    """
    row = quat_to_rotmat(np.asarray(q_wxyz, dtype=float))[..., 2, :]
    if frame == "ned":
        return -row  # type: ignore[no-any-return]
    if frame == "enu":
        return row  # type: ignore[no-any-return]
    raise ValueError(f"frame must be 'ned' or 'enu', got {frame!r}")


def angle_between_rad(a: FloatArray, b: FloatArray) -> FloatArray:
    """Angle between unit-vector rows (robust near 0 and pi)."""
    cos = np.sum(a * b, axis=-1)
    sin = np.linalg.norm(np.cross(a, b), axis=-1)
    return np.arctan2(sin, cos)  # type: ignore[no-any-return]
