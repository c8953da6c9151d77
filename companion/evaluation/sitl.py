"""Offline SITL evaluation of the estimators: JSBSim truth, simulated devices, the real decoders.

Why offline: accuracy figures need hours of simulated flight over many noise seeds and the exact
truth for every sample. The live SITL (a world process, pseudo-terminals, managed threads) runs
a few times faster than real time and its timing depends on the machine's load. Here the same
pieces are wired together in one deterministic loop, tick by tick:

* :class:`~companion.sim.flight.FlightModel` flies, steered by the scripted
  :class:`~companion.sim.pilot.Pilot` through :func:`surfaces_from_channels` at 50 Hz,
  after the same settle phase with centred sticks that ``companion.sim.world`` uses;
* :class:`~companion.sim.imu_sim.ImuSim` and :class:`~companion.sim.gps_sim.GpsSim` turn the
  truth into device bytes with their noise, bias and GPS error models; GPS epochs reach the
  decoder ``gps_latency_s`` late, as the world delivers them;
* :class:`~companion.drivers.imu_protocol.ImuDecoder` and
  :class:`~companion.drivers.gps_protocol.NmeaDecoder` (the drivers' own decoders) turn the bytes
  back into :class:`~companion.core.state.ImuSample` and :class:`~companion.core.state.GpsFix`;
* :class:`EskfAsThread` feeds :class:`~companion.estimation.eskf.Eskf` the way
  :class:`~companion.estimation.thread.EstimatorThread` does (initial phase, moving-start
  detection, GPS standard deviations and latency, horizon weighting), with the thread's own
  parameter defaults; ``tests/test_estimation_sitl.py`` checks it against the real thread
  sample by sample;
* VQF (6-D, defaults) and Madgwick (``ahrs``, default gain, IMU only) run on the same decoded
  samples.

Errors are computed against the truth at every IMU sample. Frames: the truth and the estimator
share the NED frame anchored at the flight model's start point (SITL sets the runtime's home to
it). VQF and Madgwick use a z-up earth frame with an arbitrary heading: only their inclination
(the angle between the estimated and true vertical, seen from the body) is scored.

Size: recording a flight, running each filter the way its thread does and scoring it are
one pipeline; its stages are separate functions.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.core.geo import NedFrame
from companion.core.state import GpsFix, HorizonMeasurement, ImuSample
from companion.drivers.gps import solution_to_fix
from companion.drivers.gps_protocol import NmeaDecoder
from companion.drivers.imu_protocol import ImuDecoder, ImuFast
from companion.estimation.attitude import estimate_attitude
from companion.estimation.calibration import GyroCalibration, calibration_from_row
from companion.estimation.fusion import EstimatorCore, board_to_body
from companion.estimation.quat import (
    FloatArray,
    heading_error_rad,
    inclination_error_rad,
    quat_conjugate,
    quat_from_euler,
    quat_multiply,
    quat_to_rotmat,
    quat_to_rotvec,
)
from companion.estimation.thread import estimator_param_defaults
from companion.sim.aircraft import AIRCRAFT
from companion.sim.flight import FlightModel, FlightModelError
from companion.sim.gps_sim import GpsSim, GpsSimConfig
from companion.sim.imu_model import ImuSimConfig
from companion.sim.imu_sim import ImuSim
from companion.sim.pilot import Pilot, surfaces_from_channels
from companion.sim.profiles import (
    DEFAULT_GPS_PROFILE,
    DEFAULT_IMU_PROFILE,
    DEFAULT_TURBULENCE,
    SensorSetup,
    resolve_sensors,
)
from companion.sim.scenarios import SCENARIOS

log = logging.getLogger(__name__)

__all__ = [
    "EskfAsThread",
    "EskfOptions",
    "EskfRun",
    "FilterErrors",
    "FlightSpec",
    "OutageGrowth",
    "RunResult",
    "SitlEvalError",
    "SitlRecording",
    "estimator_param_defaults",
    "evaluate",
    "filter_errors",
    "outage_growth",
    "record_flight",
    "run_attitude",
    "run_eskf",
    "run_madgwick",
    "run_vqf",
    "steady_turn_mask",
]

IMU_RATE_HZ = 100
IMU_ONLY_FILTERS = ("attitude", "vqf", "madgwick")
"""IMU-only references: the project's `estimate_attitude`, VQF 6-D and Madgwick, all defaults."""
IMU_DT_S = 1.0 / IMU_RATE_HZ
GPS_EVERY = 10
"""IMU ticks per GPS epoch (10 Hz), as in the SITL world."""
PILOT_EVERY = 2
"""IMU ticks per servo-board frame (50 Hz): how often the pilot moves the sticks."""
TEMPERATURE_EVERY = 100
"""IMU ticks between temperature readings (the IMU's slow block comes once a second)."""
CAMERA_LATENCY_S = 0.1
"""Frame time to a horizon fix reaching the estimator: detection on the ground and both links
(assumed; see docs/horizon.md)."""
GPS_IDLE_MS = 20
"""The GPS driver's default hand-off-on-silence time (GPS_IDLE_MS)."""
START_UTC_S = 12 * 3600.0
NEES_EVERY = 10
"""IMU ticks between NEES samples (10 Hz is plenty for a slowly varying statistic)."""
STEADY_TURN_BANK_RAD = math.radians(20.0)
STEADY_TURN_HOLD_S = 2.0

BoolArray = NDArray[np.bool_]


class SitlEvalError(RuntimeError):
    """The simulated flight could not be flown (trim failure, ground contact, bad options)."""


# ---------------------------------------------------------------------------------------------
# what to fly


@dataclass(frozen=True)
class FlightSpec:
    """One simulated flight and its sensor errors; ``seed`` drives every random stream.

    The seed selects the pilot's stick jitter, the IMU's turn-on biases, bias walks and noise,
    the GPS error and the horizon noise, so one seed is one "noise seed" of the benchmark.
    Horizon fixes (roll and pitch from the truth plus ``horizon_noise_rad`` of white noise) are
    always generated; an estimator run uses them only when asked to.
    """

    aircraft: str = "c172p"
    scenario: str = "turns"
    wind_ned_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    seed: int = 0
    duration_s: float = 120.0
    settle_s: float = 3.0
    """Centred sticks on the trimmed aircraft before the pilot starts (the world's settle)."""
    gps_latency_s: float | None = None
    """Mean age of a GPS epoch when its bytes reach the decoder (the world's
    ``--gps-latency``); None: the GPS profile's. The profile's jitter still applies."""
    imu_profile: str = DEFAULT_IMU_PROFILE
    """Sensor and air profiles (`companion.sim.profiles`, docs/sitl.md)."""
    gps_profile: str = DEFAULT_GPS_PROFILE
    turbulence: str = DEFAULT_TURBULENCE
    imu: ImuSimConfig | None = None
    """An explicit IMU error model instead of the profile's (None: from the profile)."""
    gps: GpsSimConfig | None = None
    """An explicit receiver instead of the profile's (None: from the profile); its own
    ``latency_s`` applies unless ``gps_latency_s`` is given."""
    horizon_rate_hz: float = 10.0
    horizon_noise_rad: float = math.radians(1.0)
    horizon_quality: float = 0.8
    horizon_latency_s: float = 0.0
    """Age of a horizon fix when it reaches the estimator (video frame time to fusion)."""
    level_calibration: bool = True
    """Level-calibrate the installation before the flight (when the IMU profile has a
    levelling error: `ImuSim.level_calibration`), as ``companion sim`` does."""
    imu_part_seed: int | None = None
    """Seed of the IMU part itself; None: from ``seed``. The part of the flight with that
    seed, switched on again (`ImuErrorModel.power_on_again`): the same scale factors,
    cross-axis terms, misalignment and temperature coefficients, a turn-on bias, noise and
    walks of this flight's own. What a calibration learnt in one flight can be tried in
    another."""
    horizon_camera: str = ""
    """``""``: horizon fixes are the truth plus ``horizon_noise_rad`` of white noise. A
    disturbance level of :class:`companion.sim.camera.SimCamera` (``none``, ``light``,
    ``thesis``): frames rendered at the true attitude, the real detector on them, its fixes
    (failures and gross errors included) handed off 0.1 s after each frame."""

    def __post_init__(self) -> None:
        if self.aircraft.lower() not in AIRCRAFT:
            raise ValueError(
                f"FlightSpec.aircraft: unknown {self.aircraft!r}, choose one of "
                f"{', '.join(sorted(AIRCRAFT))}"
            )
        if self.scenario not in SCENARIOS:
            raise ValueError(
                f"FlightSpec.scenario: unknown {self.scenario!r}, choose one of "
                f"{', '.join(SCENARIOS)}"
            )
        if len(self.wind_ned_m_s) != 3 or not all(math.isfinite(w) for w in self.wind_ned_m_s):
            raise ValueError(
                f"FlightSpec.wind_ned_m_s: need 3 finite values, got {self.wind_ned_m_s!r}"
            )
        if self.horizon_camera not in ("", "none", "light", "thesis"):
            raise ValueError(f"FlightSpec.horizon_camera: unknown {self.horizon_camera!r}, "
                             "choose '', none, light or thesis")
        checks = (
            ("duration_s", self.duration_s, 1.0, 24 * 3600.0),
            ("settle_s", self.settle_s, 0.0, 60.0),
            ("gps_latency_s", 0.0 if self.gps_latency_s is None else self.gps_latency_s,
             0.0, 0.5),
            ("horizon_rate_hz", self.horizon_rate_hz, 0.1, 100.0),
            ("horizon_noise_rad", self.horizon_noise_rad, 0.0, 1.0),
            ("horizon_quality", self.horizon_quality, 1e-3, 1.0),
            ("horizon_latency_s", self.horizon_latency_s, 0.0, 0.5),
        )
        for name, value, lo, hi in checks:
            if not (isinstance(value, int | float) and math.isfinite(value) and lo <= value <= hi):
                raise ValueError(f"FlightSpec.{name}: must be within {lo}..{hi}, got {value!r}")
        try:
            self.sensors()
        except ValueError as exc:
            raise ValueError(f"FlightSpec: {exc}") from None

    def sensors(self) -> SensorSetup:
        """The flight's IMU, receiver and air, from the profiles and any explicit override."""
        setup = resolve_sensors(self.imu_profile, self.gps_profile, self.turbulence,
                                gps_latency_s=self.gps_latency_s)
        imu = self.imu if self.imu is not None else setup.imu
        gps = setup.gps
        if self.gps is not None:
            gps = self.gps if self.gps_latency_s is None else dataclasses.replace(
                self.gps, latency_s=self.gps_latency_s)
        return dataclasses.replace(setup, imu=imu, gps=gps)


@dataclass
class SitlRecording:
    """A flown scenario: truth per IMU tick, and what the decoders delivered in each tick.

    Tick ``k`` ends at ``t_s[k] = (k + 1) / 100`` s; the truth arrays hold the state at that
    instant, and ``imu[k]`` is the sample the IMU decoder produced from that tick's frame (None
    if it produced none). ``gps`` and ``horizon`` map a tick to the fix that was handed off in
    it. True sensor biases are the simulator's, in the units the estimator estimates them.
    """

    spec: FlightSpec
    home_lla: tuple[float, float, float]
    trim_method: str
    t_s: FloatArray
    quat_true: FloatArray
    euler_true_rad: FloatArray
    pos_true_m: FloatArray
    vel_true_m_s: FloatArray
    gyro_bias_true_rad_s: FloatArray
    accel_bias_true_m_s2: FloatArray
    imu: list[ImuSample | None]
    gps: dict[int, GpsFix]
    horizon: dict[int, HorizonMeasurement]
    gps_error_ned_m: FloatArray
    """GPS position error (fix minus truth at its validity time) of every epoch, (M, 3)."""
    gps_epoch_t_s: FloatArray = field(default_factory=lambda: np.zeros(0))
    """Validity time of every epoch the receiver produced, outages included, (E,)."""
    gps_latency_true_s: FloatArray = field(default_factory=lambda: np.zeros(0))
    """How late each of those epochs was delivered (the filter is not told), (E,)."""
    gps_fix_ok: BoolArray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    """Whether each epoch had a fix (False in an outage), (E,)."""
    imu_gyro_scale: FloatArray = field(default_factory=lambda: np.zeros(3))
    """True scale-factor errors (fractions, at 25 C) and mounting misalignment (rotation vector
    from body to the part's axes, rad) of the simulated IMU."""
    imu_accel_scale: FloatArray = field(default_factory=lambda: np.zeros(3))
    imu_gyro_matrix: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))
    """The gyro's true matrix error ``M`` at the flight's mean temperature (scale factor,
    cross-axis sensitivity and mounting misalignment together): the part reads ``(I + M) w``
    plus its bias, the model the estimator's ``EST_GS_STD`` states follow."""
    imu_accel_matrix: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))
    """The accelerometer's matrix error at the same temperature, in the same convention."""
    imu_misalignment_rad: FloatArray = field(default_factory=lambda: np.zeros(3))
    imu_temperature_c: FloatArray = field(default_factory=lambda: np.zeros(0))
    """The IMU's temperature per tick, (N,)."""
    propeller_rpm: FloatArray = field(default_factory=lambda: np.zeros(0))
    """The propeller's speed per tick (drives the IMU's vibration), (N,)."""
    sensors: dict[str, Any] = field(default_factory=dict)
    """Profile names and resolved numbers (`SensorSetup.metadata`)."""
    camera: dict[str, Any] | None = None
    """The simulated camera's counts and errors (``CameraStats.summary``) when the horizon
    fixes came from the detector (``FlightSpec.horizon_camera``)."""
    level_trim: dict[str, float] = field(default_factory=dict)
    """The trims the pre-flight level calibration measured (``TRIM_ROLL``, ``TRIM_PITCH``):
    the estimator runs with them, as the runtime of ``companion sim`` does."""
    level_calibration: dict[str, float] | None = None
    """That calibration's trims and the levelling error behind them, degrees (None: none)."""

    @property
    def gyro_matrix_trimmed(self) -> FloatArray:
        """:attr:`imu_gyro_matrix` as the estimator can see it: in the board's axes turned by
        the level trims, and against the accelerometer's frame (the rotation part of its own
        matrix there), which is the frame the estimator's attitude follows. A rotation the two
        triads share, such as the board's yaw on the airframe, no estimator can see. What its
        ``EST_GS_STD`` states should approach."""
        trim = self.level_trim
        b = np.array(board_to_body(trim.get("TRIM_ROLL", 0.0), trim.get("TRIM_PITCH", 0.0),
                                   trim.get("TRIM_YAW", 0.0)))
        u, _s, vt = np.linalg.svd(b @ (np.eye(3) + self.imu_accel_matrix))
        frame = u @ vt
        return np.asarray(b @ (np.eye(3) + self.imu_gyro_matrix) @ frame.T - np.eye(3))

    @property
    def ticks(self) -> int:
        return len(self.t_s)

    def imu_arrays(self) -> tuple[FloatArray, FloatArray]:
        """Gyro and accelerometer arrays (N, 3); a missing sample repeats the previous one."""
        gyro = np.empty((self.ticks, 3))
        accel = np.empty((self.ticks, 3))
        last_g: tuple[float, float, float] = (0.0, 0.0, 0.0)
        last_a: tuple[float, float, float] = (0.0, 0.0, -9.80665)
        for k, s in enumerate(self.imu):
            if s is not None:
                last_g, last_a = s.rates_rad_s, s.accel_m_s2
            gyro[k] = last_g
            accel[k] = last_a
        return gyro, accel


def _ned_of(frame: NedFrame, lat_deg: float, lon_deg: float, alt_m: float) -> tuple[float, ...]:
    return tuple(frame.to_ned(lat_deg, lon_deg, alt_m))


def record_flight(spec: FlightSpec) -> SitlRecording:
    """Fly ``spec`` and record truth and decoded device output; deterministic for a seed.

    Raises :class:`SitlEvalError` if JSBSim cannot trim or the aircraft hits the ground.
    """
    rng = np.random.default_rng(spec.seed)
    sensors = spec.sensors()
    try:
        model = FlightModel(spec.aircraft, wind_ned_m_s=spec.wind_ned_m_s, seed=spec.seed,
                            turbulence_severity=sensors.turbulence_severity)
    except (FlightModelError, ValueError) as exc:
        raise SitlEvalError(f"{spec.aircraft} seed {spec.seed}: cannot start: {exc}") from exc
    throttle = float(model.trim_controls.throttle)
    pilot = Pilot(spec.scenario, spec.seed, aircraft=spec.aircraft, trim_throttle=throttle)
    settle_sticks = [1500, 1500, int(round(1000 + 1000 * throttle)), 1500, 1000, 1500, 1500, 1500]
    imu_sim = ImuSim.of_part(np.random.default_rng(rng.integers(2**63)), sensors.imu,
                             spec.imu_part_seed)
    gps_sim = GpsSim(np.random.default_rng(rng.integers(2**63)), sensors.gps)
    gps_every = int(round(IMU_RATE_HZ / sensors.gps.rate_hz))
    hzn_rng = np.random.default_rng(rng.integers(2**63))
    # the installation's level calibration before the flight, as companion sim makes it
    level_rng = np.random.default_rng(rng.integers(2**63))
    level_cal = imu_sim.level_calibration(level_rng) if spec.level_calibration else None
    imu_dec = ImuDecoder()
    gps_dec = NmeaDecoder(expected_sentences=sensors.gps.expected_sentences,
                          idle_handoff_ms=GPS_IDLE_MS)
    frame = model.frame

    n = int(round(spec.duration_s * IMU_RATE_HZ))
    t_s: FloatArray = (np.arange(n, dtype=float) + 1.0) * IMU_DT_S
    truth = np.empty((n, 9))  # roll, pitch, yaw, north, east, down, vn, ve, vd
    gyro_bias = np.empty((n, 3))
    accel_bias = np.empty((n, 3))
    imu: list[ImuSample | None] = [None] * n
    gps: dict[int, GpsFix] = {}
    horizon: dict[int, HorizonMeasurement] = {}
    gps_errors: list[tuple[float, ...]] = []
    gps_epochs: list[tuple[float, float, bool]] = []  # validity time, latency, fix
    temperature = np.empty(n)
    rpm = np.empty(n)
    gps_queue: list[tuple[float, bytes]] = []
    hzn_queue: list[tuple[float, HorizonMeasurement]] = []
    hzn_every = max(1, int(round(IMU_RATE_HZ / spec.horizon_rate_hz)))

    state = model.truth()
    for k in range(n):
        t_before = k * IMU_DT_S
        try:
            if k % PILOT_EVERY == 0:
                sticks = (pilot.channels_us(t_before - spec.settle_s, state)
                          if t_before >= spec.settle_s else settle_sticks)
                model.set_controls(*surfaces_from_channels(sticks))
            model.step(IMU_DT_S)
        except FlightModelError as exc:
            raise SitlEvalError(
                f"{spec.aircraft} {spec.scenario} seed {spec.seed}: flight ended at "
                f"{t_before:.2f} s: {exc}") from exc
        state = model.truth()
        t = float(t_s[k])
        t_ns = int(round(t * 1e9))
        truth[k] = (state.roll_rad, state.pitch_rad, state.yaw_rad, state.north_m, state.east_m,
                    state.down_m, state.vn_m_s, state.ve_m_s, state.vd_m_s)
        rpm[k] = model.propeller_rpm()
        temperature[k] = imu_sim.temperature_at(t)
        data = imu_sim.frame((state.p_rad_s, state.q_rad_s, state.r_rad_s),
                             (state.ax_m_s2, state.ay_m_s2, state.az_m_s2), rpm[k],
                             temperature[k])
        gyro_bias[k] = imu_sim.gyro_bias_rad_s
        accel_bias[k] = imu_sim.accel_bias_m_s2
        for item in imu_dec.feed(data, t_ns):
            if isinstance(item, ImuFast):
                imu[k] = ImuSample(t_ns, item.counter, item.rates_rad_s, item.accel_m_s2,
                                   item.gyro_ok, item.accel_ok)
        if (k + 1) % gps_every == 0:
            epoch = gps_sim.epoch(START_UTC_S + t, state.lat_deg, state.lon_deg, state.alt_m,
                                  state.vn_m_s, state.ve_m_s, state.vd_m_s,
                                  math.degrees(state.yaw_rad))
            gps_queue.append((t + gps_sim.last_latency_s, epoch))
            gps_epochs.append((t, gps_sim.last_latency_s, not gps_sim.in_outage))
            sol = gps_sim.last_solution
            if sol is not None and sol.lat_deg is not None and sol.lon_deg is not None \
                    and sol.alt_m is not None:
                fix_ned = _ned_of(frame, sol.lat_deg, sol.lon_deg, sol.alt_m)
                gps_errors.append((fix_ned[0] - state.north_m, fix_ned[1] - state.east_m,
                                   fix_ned[2] - state.down_m))
        if (k + 1) % hzn_every == hzn_every // 2:
            noise = hzn_rng.normal(0.0, spec.horizon_noise_rad, 2) if spec.horizon_noise_rad \
                else np.zeros(2)
            meas = HorizonMeasurement(t_ns, state.roll_rad + float(noise[0]),
                                      state.pitch_rad + float(noise[1]), spec.horizon_quality,
                                      "sitl_eval")
            hzn_queue.append((t + spec.horizon_latency_s, meas))
        while gps_queue and gps_queue[0][0] <= t + 1e-9:
            _, data = gps_queue.pop(0)
            for sol in gps_dec.feed(data, t_ns) + gps_dec.poll(t_ns):
                gps[k] = solution_to_fix(sol, t_ns)
        for sol in gps_dec.poll(t_ns):
            gps[k] = solution_to_fix(sol, t_ns)
        while hzn_queue and hzn_queue[0][0] <= t + 1e-9:
            horizon[k] = hzn_queue.pop(0)[1]

    quat = quat_from_euler(truth[:, 0], truth[:, 1], truth[:, 2])
    camera = None
    if spec.horizon_camera:
        # the camera does not feed back into the flight, so it can run over the finished truth
        from companion.sim.camera import SimCamera, camera_seed, horizon_measurements

        cam = SimCamera(camera_seed(spec.seed), rate_hz=spec.horizon_rate_hz,
                        latency_s=CAMERA_LATENCY_S, disturbance=spec.horizon_camera)
        horizon = horizon_measurements(cam, t_s, truth[:, 0:3])
        camera = cam.stats.summary()
    matrices = imu_sim.errors.scale_matrices(
        float(np.mean(temperature)) if len(temperature) else 25.0)
    return SitlRecording(
        spec=spec,
        home_lla=(frame.lat0_deg, frame.lon0_deg, frame.alt0_m),
        trim_method=model.trim_method,
        t_s=t_s,
        quat_true=quat,
        euler_true_rad=truth[:, 0:3].copy(),
        pos_true_m=truth[:, 3:6].copy(),
        vel_true_m_s=truth[:, 6:9].copy(),
        gyro_bias_true_rad_s=gyro_bias,
        accel_bias_true_m_s2=accel_bias,
        imu=imu,
        gps=gps,
        horizon=horizon,
        gps_error_ned_m=np.array(gps_errors).reshape(-1, 3),
        gps_epoch_t_s=np.array([e[0] for e in gps_epochs]),
        gps_latency_true_s=np.array([e[1] for e in gps_epochs]),
        gps_fix_ok=np.array([e[2] for e in gps_epochs], dtype=bool),
        imu_gyro_scale=np.array(imu_sim.errors.gyro_scale),
        imu_accel_scale=np.array(imu_sim.errors.accel_scale),
        imu_gyro_matrix=np.array(matrices[0]) - np.eye(3),
        imu_accel_matrix=np.array(matrices[1]) - np.eye(3),
        imu_misalignment_rad=np.array(imu_sim.errors.misalignment_rad),
        imu_temperature_c=temperature,
        propeller_rpm=rpm,
        sensors=sensors.metadata(),
        camera=camera,
        level_trim={k.removeprefix("EST_"): v for k, v in level_cal.params().items()}
        if level_cal is not None else {},
        level_calibration=level_cal.metadata() if level_cal is not None else None,
    )


# ---------------------------------------------------------------------------------------------
# the project's estimator, fed as the estimator thread feeds it


class EskfAsThread(EstimatorCore):
    """:class:`EstimatorCore`, the code the estimator thread runs, with the thread's defaults.

    ``params`` overrides thread parameters by suffix (unknown names are refused);
    ``eskf_kwargs`` are added to the keyword arguments given to :class:`Eskf` (a tuning
    experiment, not a thread feature). :meth:`cycle` is one thread cycle.
    """

    def __init__(
        self,
        home_lla: tuple[float, float, float] | None,
        *,
        params: Mapping[str, float] | None = None,
        eskf_kwargs: Mapping[str, float] | None = None,
    ) -> None:
        defaults = estimator_param_defaults()
        given = dict(params or {})
        unknown = sorted(set(given) - set(defaults))
        if unknown:
            raise ValueError(
                f"EskfAsThread: unknown estimator parameter(s) {unknown}; known: {sorted(defaults)}"
            )
        super().__init__({**defaults, **given}, home_lla, eskf_kwargs=eskf_kwargs)


@dataclass(frozen=True)
class EskfOptions:
    """One way of running the project's estimator on a recording."""

    horizon: bool = False
    """Deliver the recording's horizon fixes to the estimator."""
    gps_outage_s: tuple[float, float] | None = None
    """GPS fixes handed off within [start, end) seconds are withheld (the receiver lost them)."""
    params: Mapping[str, float] = field(default_factory=dict)
    eskf_kwargs: Mapping[str, float] = field(default_factory=dict)
    check_pd_every: int = 1
    """IMU ticks between explicit Cholesky checks of the covariance (1: every sample)."""
    heading_std_rad: float = 0.0
    """With each GPS fix, also fuse a heading fix of the airframe: the true heading plus this
    much white noise (0: none). Stands for a heading sensor the simulated aircraft does not
    carry (a dual-antenna receiver, a calibrated magnetometer): what one would buy."""
    heading_bias_rad: float = 0.0
    """A constant error of those heading fixes (a magnetometer's declination or interference
    error, a dual-antenna baseline's mounting error), told to nobody."""
    measure_cpu: bool = False
    """Also take the thread CPU time of every step (``step_cpu_us``); the clock read costs
    tens of microseconds here, so only the timing study asks for it."""


@dataclass
class EskfRun:
    """Per-tick output of one estimator run (NaN before the filter started)."""

    quat: FloatArray
    pos_m: FloatArray
    vel_m_s: FloatArray
    gyro_bias_rad_s: FloatArray
    accel_bias_m_s2: FloatArray
    step_us: NDArray[np.float32]
    """Wall time of each cycle: predict, any updates and the state snapshot the thread
    publishes (NaN before the start)."""
    filter_us: NDArray[np.float32]
    """The same without the snapshot: the filter's own predict and updates."""
    step_cpu_us: NDArray[np.float32]
    """CPU time of this thread for the same work as ``step_us`` (NaN unless measured): on a
    shared machine the wall time also counts the time the scheduler gave to other processes."""
    update_tick: BoolArray
    """Ticks in which a GPS fix was fused (or tried)."""
    nees_t_s: FloatArray
    nees: FloatArray
    """Normalised estimation error squared over all 15 error states, every NEES_EVERY ticks."""
    nees_blocks: FloatArray
    """NEES of each 3-state block alone (position, velocity, attitude, gyro bias, accel bias)."""
    start_tick: int
    faults: int
    fault_reasons: list[str]
    pd_checks: int
    pd_failures: int
    non_finite: int
    """Ticks with a non-finite state value (should stay 0)."""
    exceptions: int
    """Exceptions out of the filter: each would have cost the thread a restart (should stay 0)."""
    gps_accepted: int
    gps_rejected: int
    horizon_used: int
    moving_start: bool
    gyro_matrix: FloatArray = field(default_factory=lambda: np.zeros((0, 9)))
    """The estimated gyro matrix error ``M`` (row-major) per tick, NaN before the start; once
    a second (every ``GYRO_MATRIX_EVERY`` ticks) after :func:`evaluate` compacts the run."""
    learnt: GyroCalibration | None = None
    """What the filter had learnt of the gyro at the end (None if it never ran): what
    ``companion estimation calibration`` would hand to the next flight."""


HEADING_SEED_OFFSET = 7919
"""The heading fixes' noise has its own stream, seeded from the flight's seed plus this."""
GYRO_MATRIX_EVERY = 100
"""Ticks between the gyro-matrix estimates a compacted run keeps (1 s at 100 Hz)."""


def _no_clock() -> int:
    return 0


def _pd(p: FloatArray, yaw_aligned: bool) -> bool:
    sub = p if yaw_aligned else np.delete(np.delete(p, 8, axis=0), 8, axis=1)
    try:
        np.linalg.cholesky(sub)
    except np.linalg.LinAlgError:
        return False
    return True


def _error_state(rec: SitlRecording, k: int, st_q: FloatArray, pos: FloatArray, vel: FloatArray,
                 bg: FloatArray, ba: FloatArray) -> FloatArray:
    """True minus estimated error state in the ESKF's convention (q_true = exp(dtheta) * q)."""
    dq = quat_multiply(rec.quat_true[k], quat_conjugate(st_q))
    return np.concatenate((rec.pos_true_m[k] - pos, rec.vel_true_m_s[k] - vel,
                           quat_to_rotvec(dq), rec.gyro_bias_true_rad_s[k] - bg,
                           rec.accel_bias_true_m_s2[k] - ba))


def run_eskf(rec: SitlRecording, options: EskfOptions | None = None) -> EskfRun:
    """Run the project's estimator over a recording, as the estimator thread would."""
    opts = options or EskfOptions()
    # the trims the flight's level calibration set, unless the options name their own
    est = EskfAsThread(rec.home_lla, params={**rec.level_trim, **opts.params},
                       eskf_kwargs=opts.eskf_kwargs)
    n = rec.ticks
    quat = np.full((n, 4), np.nan)
    pos = np.full((n, 3), np.nan)
    vel = np.full((n, 3), np.nan)
    bg = np.full((n, 3), np.nan)
    ba = np.full((n, 3), np.nan)
    gm = np.full((n, 9), np.nan)
    step_us = np.full(n, np.nan, dtype=np.float32)
    filter_us = np.full(n, np.nan, dtype=np.float32)
    step_cpu_us = np.full(n, np.nan, dtype=np.float32)
    update_tick = np.zeros(n, dtype=bool)
    nees_t: list[float] = []
    nees: list[float] = []
    blocks: list[FloatArray] = []
    start = -1
    pd_checks = pd_failures = non_finite = exceptions = 0
    outage = opts.gps_outage_s
    every = max(1, int(opts.check_pd_every))
    perf = time.perf_counter_ns
    cpu = time.thread_time_ns if opts.measure_cpu else _no_clock
    heading_rng = np.random.default_rng(rec.spec.seed + HEADING_SEED_OFFSET)
    for k in range(n):
        sample = rec.imu[k]
        fix = rec.gps.get(k)
        t = float(rec.t_s[k])
        if fix is not None and outage is not None and outage[0] <= t < outage[1]:
            fix = None
        hzn = rec.horizon.get(k) if opts.horizon else None
        samples = [sample] if sample is not None else []
        c0 = cpu()
        t0 = perf()
        try:
            if k % TEMPERATURE_EVERY == 0 and len(rec.imu_temperature_c) > k:
                # the slow block's temperature, once a second at its 0.01 C resolution
                est.set_temperature(round(float(rec.imu_temperature_c[k]), 2))
            running = est.cycle(samples, fix, hzn)
            if opts.heading_std_rad > 0.0 and fix is not None and est.filter is not None:
                est.filter.update_heading(
                    float(rec.euler_true_rad[k, 2]) + opts.heading_bias_rad
                    + opts.heading_std_rad * float(heading_rng.standard_normal()),
                    opts.heading_std_rad)
            t1 = perf()
            f = est.filter
            st = f.state() if f is not None and running else None
        except Exception:  # the thread would crash and be restarted: count, never hide
            log.exception("estimator raised at t=%.2f s", t)
            exceptions += 1
            continue
        t2 = perf()
        c2 = cpu()
        if st is None or f is None:
            continue
        if start < 0:
            start = k
        else:
            step_us[k] = (t2 - t0) / 1e3
            filter_us[k] = (t1 - t0) / 1e3
            if opts.measure_cpu:
                step_cpu_us[k] = (c2 - c0) / 1e3
        update_tick[k] = fix is not None
        quat[k], pos[k], vel[k] = st.quaternion, st.pos_ned_m, st.vel_ned_m_s
        bg[k], ba[k] = st.gyro_bias_rad_s, st.accel_bias_m_s2
        gm[k] = st.gyro_matrix.reshape(-1)
        if not (np.isfinite(quat[k]).all() and np.isfinite(pos[k]).all()
                and np.isfinite(vel[k]).all()):
            non_finite += 1
        if k % every == 0 or fix is not None:
            pd_checks += 1
            # the 15 navigation states (marginal): the GPS delay has no truth to score here
            p = f.covariance[:15, :15]
            if not (np.isfinite(p).all() and _pd(p, st.yaw_aligned)):
                pd_failures += 1
                continue
            if k % NEES_EVERY == 0 and st.yaw_aligned:
                e = _error_state(rec, k, st.quaternion, st.pos_ned_m, st.vel_ned_m_s,
                                 st.gyro_bias_rad_s, st.accel_bias_m_s2)
                nees_t.append(t)
                nees.append(float(e @ np.linalg.solve(p, e)))
                blocks.append(np.array([
                    float(e[i:i + 3] @ np.linalg.solve(p[i:i + 3, i:i + 3], e[i:i + 3]))
                    for i in range(0, 15, 3)]))
    f = est.filter
    return EskfRun(
        quat=quat, pos_m=pos, vel_m_s=vel, gyro_bias_rad_s=bg, accel_bias_m_s2=ba,
        step_us=step_us, filter_us=filter_us,
        step_cpu_us=step_cpu_us, update_tick=update_tick,
        nees_t_s=np.array(nees_t), nees=np.array(nees),
        nees_blocks=np.array(blocks).reshape(-1, 5),
        start_tick=start,
        faults=f.faults if f is not None else 0,
        fault_reasons=[fl.reason for fl in f.fault_log] if f is not None else [],
        pd_checks=pd_checks, pd_failures=pd_failures, non_finite=non_finite,
        exceptions=exceptions, gps_accepted=est.gps_accepted, gps_rejected=est.gps_rejected,
        horizon_used=est.horizon_used, moving_start=est.moving_start, gyro_matrix=gm,
        learnt=(calibration_from_row([v for part in f.gyro_calibration() for v in part],
                                     float(rec.t_s[-1] - rec.t_s[max(start, 0)]))
                if f is not None and start >= 0 else None),
    )


# ---------------------------------------------------------------------------------------------
# IMU-only references


def _first_level_quat_zup(accel: FloatArray) -> FloatArray:
    """A z-up-frame quaternion that makes the first specific force read as 'up'."""
    a = accel[0] / np.linalg.norm(accel[0])
    roll = math.atan2(-a[1], -a[2])
    pitch = math.atan2(a[0], math.hypot(a[1], a[2]))
    q_ned = quat_from_euler(roll, pitch, 0.0)
    # body -> NED, then NED -> (north, west, up): a half turn about north
    return np.asarray(quat_multiply((0.0, 1.0, 0.0, 0.0), q_ned))


def run_attitude(rec: SitlRecording) -> FloatArray:
    """The project's IMU-only filter (`estimate_attitude`, defaults) on the decoded samples; NED.

    It sees exactly what VQF and Madgwick see (gyro and accelerometer, nothing else), so its row
    is the like-for-like comparison; the GPS/INS estimator also uses GPS and knows its latency."""
    gyro, accel = rec.imu_arrays()
    return estimate_attitude(gyro, accel, float(IMU_RATE_HZ))


def run_vqf(rec: SitlRecording) -> FloatArray:
    """VQF, 6-D, default parameters, on the decoded samples: (N, 4) quaternions, z-up frame."""
    from vqf import VQF

    gyro, accel = rec.imu_arrays()
    filt = VQF(IMU_DT_S)
    out = filt.updateBatch(np.ascontiguousarray(gyro), np.ascontiguousarray(accel))
    return np.asarray(out["quat6D"], dtype=float)


def run_madgwick(rec: SitlRecording) -> FloatArray:
    """Madgwick (``ahrs``), IMU only, default gain, on the decoded samples; z-up frame."""
    from ahrs.filters import Madgwick

    gyro, accel = rec.imu_arrays()
    filt = Madgwick(frequency=float(IMU_RATE_HZ))
    q = _first_level_quat_zup(accel)
    out = np.empty((rec.ticks, 4))
    for k in range(rec.ticks):
        q = filt.updateIMU(q, gyro[k], accel[k])
        out[k] = q
    return out


def inclination_error_zup_rad(q_zup: FloatArray, q_true_ned: FloatArray) -> FloatArray:
    """Tilt error of a z-up-frame estimate against the NED truth (heading-free)."""
    up_est = quat_to_rotmat(q_zup)[..., 2, :]
    down_true = quat_to_rotmat(q_true_ned)[..., 2, :]
    cos_a = np.sum(-up_est * down_true, axis=-1)
    sin_a = np.linalg.norm(np.cross(-up_est, down_true), axis=-1)
    return np.arctan2(sin_a, cos_a)


# ---------------------------------------------------------------------------------------------
# errors


@dataclass
class FilterErrors:
    """Per-tick errors of one filter against the truth (NaN where it had no estimate)."""

    inclination_rad: FloatArray
    heading_rad: FloatArray | None = None
    vel_m_s: FloatArray | None = None
    """Norm of the 3-D velocity error."""
    hpos_m: FloatArray | None = None
    """Norm of the horizontal position error."""
    non_finite: int = 0


def filter_errors(rec: SitlRecording, quat: FloatArray, *, zup: bool = False,
                  run: EskfRun | None = None) -> FilterErrors:
    """Errors of an estimate against the recording's truth; ``run`` adds heading/vel/pos."""
    finite = np.isfinite(quat).all(axis=1)
    incl = np.full(rec.ticks, np.nan)
    if zup:
        incl[finite] = inclination_error_zup_rad(quat[finite], rec.quat_true[finite])
        started = np.ones(rec.ticks, dtype=bool)
    else:
        incl[finite] = inclination_error_rad(quat[finite], rec.quat_true[finite])
        started = np.arange(rec.ticks) >= (run.start_tick if run is not None and
                                          run.start_tick >= 0 else rec.ticks)
    non_finite = int(np.count_nonzero(started & ~finite))
    if run is None:
        return FilterErrors(incl, non_finite=non_finite)
    heading = np.full(rec.ticks, np.nan)
    heading[finite] = heading_error_rad(quat[finite], rec.quat_true[finite])
    vel = np.linalg.norm(run.vel_m_s - rec.vel_true_m_s, axis=1)
    hpos = np.linalg.norm(run.pos_m[:, :2] - rec.pos_true_m[:, :2], axis=1)
    return FilterErrors(incl, heading, vel, hpos, non_finite)


def steady_turn_mask(rec: SitlRecording, bank_rad: float = STEADY_TURN_BANK_RAD,
                     hold_s: float = STEADY_TURN_HOLD_S) -> BoolArray:
    """Ticks where the true bank has stayed beyond ``bank_rad`` for the last ``hold_s``."""
    banked = np.abs(rec.euler_true_rad[:, 0]) > bank_rad
    window = max(1, int(round(hold_s * IMU_RATE_HZ)))
    unbanked = np.concatenate(([0], np.cumsum(~banked)))
    k = np.arange(rec.ticks)
    lo = np.maximum(k + 1 - window, 0)
    held = (unbanked[k + 1] - unbanked[lo]) == 0
    return banked & held & (k + 1 >= window)


@dataclass(frozen=True)
class OutageGrowth:
    """How far the estimate drifted during a GPS outage (errors at its end and worst within)."""

    before_incl_deg: float
    end_incl_deg: float
    max_incl_deg: float
    before_heading_deg: float
    end_heading_deg: float
    before_vel_m_s: float
    end_vel_m_s: float
    before_hpos_m: float
    end_hpos_m: float
    max_hpos_m: float
    recovered_hpos_m: float
    """Horizontal position error 10 s after the outage ended."""


def outage_growth(rec: SitlRecording, err: FilterErrors, window_s: tuple[float, float],
                  before_s: float = 5.0) -> OutageGrowth:
    """Errors just before (mean over ``before_s``), at the end of and within an outage."""
    if err.heading_rad is None or err.vel_m_s is None or err.hpos_m is None:
        raise ValueError("outage_growth needs the errors of a navigation filter (run=...)")
    t = rec.t_s
    t0, t1 = window_s
    before = (t >= t0 - before_s) & (t < t0)
    inside = (t >= t0) & (t < t1)
    if not before.any() or not inside.any():
        raise ValueError(f"outage window {window_s} is not inside the recording (0..{t[-1]:.1f} s)")
    end = int(np.nonzero(inside)[0][-1])
    after = min(int(np.searchsorted(t, t1 + 10.0)), len(t) - 1)
    deg = math.degrees

    def mean(x: FloatArray) -> float:
        return float(np.nanmean(np.abs(x[before])))

    return OutageGrowth(
        before_incl_deg=deg(mean(err.inclination_rad)),
        end_incl_deg=deg(float(err.inclination_rad[end])),
        max_incl_deg=deg(float(np.nanmax(err.inclination_rad[inside]))),
        before_heading_deg=deg(mean(err.heading_rad)),
        end_heading_deg=deg(abs(float(err.heading_rad[end]))),
        before_vel_m_s=mean(err.vel_m_s),
        end_vel_m_s=float(err.vel_m_s[end]),
        before_hpos_m=mean(err.hpos_m),
        end_hpos_m=float(err.hpos_m[end]),
        max_hpos_m=float(np.nanmax(err.hpos_m[inside])),
        recovered_hpos_m=float(err.hpos_m[after]),
    )


# ---------------------------------------------------------------------------------------------
# one benchmark job


@dataclass
class RunResult:
    """Everything a benchmark needs from one recording, compact enough to pass between processes.

    Error series are float32 (the pooled statistics do not need more) and keyed by filter name:
    ``vqf`` and ``madgwick`` for the IMU-only references, the :func:`evaluate` variant names for
    the project's estimator.
    """

    spec: FlightSpec
    trim_method: str
    t_s: NDArray[np.float32]
    bank_rad: NDArray[np.float32]
    steady_turn: BoolArray
    gps_error_h_m: NDArray[np.float32]
    """(M, 2): validity time (s) and horizontal error (m) of every GPS fix, the floor under any
    GPS/INS position error (the simulated receiver's error wanders like a real one's)."""
    errors: dict[str, FilterErrors]
    eskf: dict[str, EskfRun]
    outage: dict[str, OutageGrowth]
    elapsed_s: float
    camera: dict[str, Any] | None = None
    """The camera's figures when the horizon fixes came from the detector."""
    gyro_matrix_true: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))
    """The simulated gyro's matrix error in the estimator's axes
    (:attr:`SitlRecording.gyro_matrix_trimmed`)."""


def _compact(run: EskfRun) -> EskfRun:
    """Drop the per-tick state arrays (errors keep what matters) before pickling."""
    empty = np.zeros((0, 3))
    return EskfRun(
        quat=np.zeros((0, 4)), pos_m=empty, vel_m_s=empty, gyro_bias_rad_s=empty,
        accel_bias_m_s2=empty, step_us=run.step_us, filter_us=run.filter_us,
        step_cpu_us=run.step_cpu_us, update_tick=run.update_tick,
        nees_t_s=run.nees_t_s, nees=run.nees, nees_blocks=run.nees_blocks,
        start_tick=run.start_tick, faults=run.faults, fault_reasons=run.fault_reasons,
        pd_checks=run.pd_checks, pd_failures=run.pd_failures, non_finite=run.non_finite,
        exceptions=run.exceptions, gps_accepted=run.gps_accepted, gps_rejected=run.gps_rejected,
        horizon_used=run.horizon_used, moving_start=run.moving_start,
        gyro_matrix=run.gyro_matrix[::GYRO_MATRIX_EVERY].copy(), learnt=run.learnt)


def _f32(errors: FilterErrors) -> FilterErrors:
    def c(x: FloatArray | None) -> FloatArray | None:
        return None if x is None else x.astype(np.float32)  # type: ignore[return-value]

    return FilterErrors(c(errors.inclination_rad), c(errors.heading_rad),  # type: ignore[arg-type]
                        c(errors.vel_m_s), c(errors.hpos_m), errors.non_finite)


def evaluate(
    spec: FlightSpec,
    variants: Mapping[str, EskfOptions] | None = None,
    imu_only: Sequence[str] = IMU_ONLY_FILTERS,
    compact: bool = True,
) -> RunResult:
    """Fly ``spec`` once and score every estimator variant and IMU-only reference on it.

    ``variants`` maps a name to :class:`EskfOptions` (default: ``{"eskf": EskfOptions()}``);
    a variant with a GPS outage also gets its :class:`OutageGrowth`. ``compact`` drops the
    per-tick estimates and keeps the error series (what a multi-process benchmark sends back).
    """
    t0 = time.perf_counter()
    chosen = dict(variants) if variants is not None else {"eskf": EskfOptions()}
    unknown = sorted(set(imu_only) - set(IMU_ONLY_FILTERS))
    if unknown:
        raise ValueError(f"evaluate: unknown IMU-only filter(s) {unknown}; "
                         f"use {', '.join(IMU_ONLY_FILTERS)}")
    rec = record_flight(spec)
    errors: dict[str, FilterErrors] = {}
    runs: dict[str, EskfRun] = {}
    outage: dict[str, OutageGrowth] = {}
    for name, opts in chosen.items():
        run = run_eskf(rec, opts)
        err = filter_errors(rec, run.quat, run=run)
        if opts.gps_outage_s is not None:
            outage[name] = outage_growth(rec, err, opts.gps_outage_s)
        errors[name] = _f32(err) if compact else err
        runs[name] = _compact(run) if compact else run
    if "attitude" in imu_only:
        err = filter_errors(rec, run_attitude(rec))
        errors["attitude"] = _f32(err) if compact else err
    if "vqf" in imu_only:
        err = filter_errors(rec, run_vqf(rec), zup=True)
        errors["vqf"] = _f32(err) if compact else err
    if "madgwick" in imu_only:
        err = filter_errors(rec, run_madgwick(rec), zup=True)
        errors["madgwick"] = _f32(err) if compact else err
    gps_h = np.linalg.norm(rec.gps_error_ned_m[:, :2], axis=1)
    return RunResult(
        spec=spec,
        trim_method=rec.trim_method,
        t_s=rec.t_s.astype(np.float32),
        bank_rad=rec.euler_true_rad[:, 0].astype(np.float32),
        steady_turn=steady_turn_mask(rec),
        gps_error_h_m=np.concatenate((rec.t_s[GPS_EVERY - 1::GPS_EVERY][:len(gps_h)][:, None],
                                      gps_h[:, None]), axis=1).astype(np.float32),
        errors=errors,
        eskf=runs,
        outage=outage,
        elapsed_s=time.perf_counter() - t0,
        camera=rec.camera,
        gyro_matrix_true=rec.gyro_matrix_trimmed,
    )
