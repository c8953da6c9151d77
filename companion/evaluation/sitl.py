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
* :class:`~companion.evaluation.sitl_estimator.EskfAsThread` feeds :class:`~companion.estimation.eskf.Eskf` the way
  :class:`~companion.estimation.thread.EstimatorThread` does (initial phase, moving-start
  detection, GPS standard deviations and latency, horizon weighting), with the thread's own
  parameter defaults; ``tests/test_estimation_sitl.py`` checks it against the real thread
  sample by sample;
* VQF (6-D, defaults) and Madgwick (``ahrs``, default gain, IMU only) run on the same decoded
  samples.

This module records the flight (:func:`record_flight`); the estimator runs as the thread runs
it in :mod:`companion.evaluation.sitl_estimator`, the IMU-only references through
:mod:`companion.estimation.imu_filters`, the errors are scored in
:mod:`companion.evaluation.sitl_scoring`, and :mod:`companion.evaluation.sitl_benchmark` does
all of it for one benchmark job.

Errors are computed against the truth at every IMU sample. Frames: the truth and the estimator
share the NED frame anchored at the flight model's start point (SITL sets the runtime's home to
it). VQF and Madgwick use a z-up earth frame with an arbitrary heading: only their inclination
(the angle between the estimated and true vertical, seen from the body) is scored.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.core.geo import NedFrame
from companion.core.state import GpsFix, HorizonMeasurement, ImuSample
from companion.drivers.gps import solution_to_fix
from companion.drivers.gps_protocol import NmeaDecoder
from companion.drivers.imu_protocol import ImuDecoder, ImuFast
from companion.estimation.fusion import board_to_body
from companion.estimation.quat import (
    FloatArray,
    quat_from_euler,
)
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

IMU_RATE_HZ = 100
IMU_DT_S = 1.0 / IMU_RATE_HZ
GPS_EVERY = 10
"""IMU ticks per GPS epoch (10 Hz), as in the SITL world."""
PILOT_EVERY = 2
"""IMU ticks per servo-board frame (50 Hz): how often the pilot moves the sticks."""
CAMERA_LATENCY_S = 0.1
"""Frame time to a horizon fix reaching the estimator: detection on the ground and both links
(assumed; see docs/horizon.md)."""
GPS_IDLE_MS = 20
"""The GPS driver's default hand-off-on-silence time (GPS_IDLE_MS)."""
START_UTC_S = 12 * 3600.0

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
