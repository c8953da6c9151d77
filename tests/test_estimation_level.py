"""Level calibration: the trims from a still, level aircraft; the bias they took for a tilt;
the simulated installation's calibration; the command from a ground station."""

from __future__ import annotations

import dataclasses
import math
import re
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from conftest import free_udp_port, wait_for
from support.synthetic_vehicle import MiniGcs

from companion.core.params import ParamRegistry
from companion.core.state import ImuSample
from companion.estimation.eskf import Eskf
from companion.estimation.fusion import EstimatorCore
from companion.estimation.level import LevelCalibrationError, level_trim
from companion.estimation.thread import EstimatorThread
from companion.sim.imu_model import ImuSimConfig, rotation_matrix
from companion.sim.imu_sim import ImuSim
from companion.sim.profiles import imu_profile
from companion.vehicle import VEHICLE
from companion.watchdog import ManagedThread, RuntimeContext, ThreadManager
from gcs_bridge.bridge import MavlinkBridge
from gcs_bridge.dialect import mavlink

G = 9.80665
LEVEL = np.array([0.0, 0.0, -G])


def _board(roll_deg: float, pitch_deg: float, yaw_deg: float = 0.0) -> np.ndarray:
    """The simulator's mounting convention: part axes = M body axes."""
    return np.array(rotation_matrix(tuple(math.radians(a)  # type: ignore[arg-type]
                                          for a in (roll_deg, pitch_deg, yaw_deg))))


def _still(m: np.ndarray, n: int = 200, noise: float = 0.02, rate_noise: float = 0.002,
           seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    accel = (m @ LEVEL) + rng.normal(0.0, noise, (n, 3))
    rates = rng.normal(0.0, rate_noise, (n, 3))
    return accel, rates


def _core(**params: float) -> EstimatorCore:
    p = {s.name.removeprefix("EST_"): float(s.default)
         for s in EstimatorThread.declare_params("EST")}
    p.update(params)
    return EstimatorCore(p, (47.0, 8.0, 500.0))


@pytest.mark.parametrize("angles", [(0.8, -0.5, 0.0), (-2.0, 1.5, 0.0), (1.0, 1.0, 20.0)])
def test_trims_turn_the_boards_gravity_back_to_the_airframes_z(angles: tuple[float, ...]
                                                                ) -> None:
    m = _board(*angles)
    accel, rates = _still(m)
    trim = level_trim(accel.tolist(), rates.tolist())
    assert trim.samples == 200
    # the board's yaw is invisible level: the trims keep any yaw trim given beforehand
    core = _core(TRIM_ROLL=trim.roll_rad, TRIM_PITCH=trim.pitch_rad,
                 TRIM_YAW=math.radians(angles[2]))
    (s,) = core._to_body([ImuSample(0, 0, (0.0, 0.0, 0.0), tuple(m @ LEVEL))])  # type: ignore[arg-type]
    tilt = math.degrees(math.atan2(math.hypot(s.accel_m_s2[0], s.accel_m_s2[1]),
                                   -s.accel_m_s2[2]))
    assert tilt < 0.01  # the noise averaged over 200 samples: well under a hundredth
    if angles[2] == 0.0:  # one-axis-at-a-time angles: the trims are the board's own
        assert math.degrees(trim.roll_rad) == pytest.approx(angles[0], abs=0.01)
        assert math.degrees(trim.pitch_rad) == pytest.approx(angles[1], abs=0.02)


@pytest.mark.parametrize(("change", "words"), [
    ({"rate_noise": 0.2}, "moving"),
    ({"noise": 1.5}, "not still"),
    ({"n": 20}, "at least 50"),
])
def test_a_moving_or_short_reading_is_refused_with_its_figure(change: dict[str, float],
                                                                words: str) -> None:
    accel, rates = _still(_board(0.5, 0.5), **change)  # type: ignore[arg-type]
    with pytest.raises(LevelCalibrationError, match=words):
        level_trim(accel.tolist(), rates.tolist())


def test_a_reading_that_is_not_1g_or_tilted_beyond_the_range_is_refused() -> None:
    accel, rates = _still(_board(0.0, 0.0))
    with pytest.raises(LevelCalibrationError, match=r"gravity reads 4\.9"):
        level_trim((accel * 0.5).tolist(), rates.tolist())
    accel, rates = _still(_board(40.0, 0.0))
    with pytest.raises(LevelCalibrationError, match="upright"):
        level_trim(accel.tolist(), rates.tolist())
    accel[3, 1] = math.nan
    with pytest.raises(LevelCalibrationError, match="not finite"):
        level_trim(accel.tolist(), rates.tolist())


# ----------------------------------------------------------------------- the bias it took


def test_the_reported_attitude_gives_back_the_tilt_of_the_learnt_bias() -> None:
    f = Eskf()
    assert f.initialise(LEVEL, np.zeros(3), np.zeros(3), np.zeros(3))
    f._set_biases(np.zeros(3), np.array([0.05, -0.03, 0.2]))
    plain = f.flight_view()
    f.trim_bias_tilt = True
    turned = f.flight_view()
    state = f.state()
    # b_x tilts by b_x / g in pitch, b_y by -b_y / g in roll; b_z is no tilt
    assert math.degrees(turned.pitch_rad - plain.pitch_rad) == pytest.approx(
        math.degrees(0.05 / G), abs=1e-4)
    assert math.degrees(turned.roll_rad - plain.roll_rad) == pytest.approx(
        math.degrees(0.03 / G), abs=1e-4)
    assert state.pitch_rad == pytest.approx(turned.pitch_rad, abs=1e-12)
    assert f._q != turned.quaternion  # only what is reported turns


def test_a_horizon_fix_is_held_against_the_reported_attitude() -> None:
    """The camera sees the airframe: a fix equal to what is reported leaves nothing to correct."""
    f = Eskf()
    assert f.initialise(LEVEL, np.zeros(3), np.zeros(3), np.zeros(3))
    f._set_biases(np.zeros(3), np.array([0.05, -0.03, 0.0]))
    f.trim_bias_tilt = True
    v = f.flight_view()
    res = f.update_attitude(v.roll_rad, v.pitch_rad, 1.0)
    assert res.accepted and np.abs(res.innovation).max() < 1e-9
    f.trim_bias_tilt = False  # the filter's own frame is the tilt of the bias away
    res = f.update_attitude(v.roll_rad, v.pitch_rad, 1.0)
    assert np.abs(res.innovation).max() > 0.5 * 0.05 / G


def test_trim_bias_follows_the_parameters_and_needs_a_trim() -> None:
    core = _core()
    f = core.new_filter(False)
    assert f.trim_bias_tilt is False  # no level calibration: no trim took a bias
    core.filter = f
    core.update_params({"TRIM_PITCH": 0.01})
    assert f.trim_bias_tilt is True
    core.update_params({"TRIM_BIAS": 0})
    assert f.trim_bias_tilt is False


def test_new_trims_restart_the_levelling_or_turn_a_running_filter() -> None:
    core = _core()
    level = ImuSample(0, 0, (0.0, 0.0, 0.0), (0.0, 0.0, -G))
    core.initial_phase([level] * 10, None)
    assert core._accel
    core.update_params({"TRIM_ROLL": 0.01})
    assert not core._accel  # averaged under the old trim: not used
    core = _core()
    f = core.new_filter(False)
    assert f.initialise(LEVEL, np.zeros(3), np.zeros(3), np.zeros(3))
    core.filter = f
    core.update_params({"TRIM_BIAS": 0})
    before = f.flight_view().pitch_rad
    core.update_params({"TRIM_PITCH": math.radians(2.0)})
    # a board pitched up 2 deg was taken for the aircraft: the aircraft is 2 deg lower
    assert math.degrees(f.flight_view().pitch_rad - before) == pytest.approx(-2.0, abs=1e-6)


# ----------------------------------------------------------------------- in the simulator


def test_the_simulated_calibration_reads_the_parts_own_tilt_and_moves_no_flight_draw() -> None:
    cfg = dataclasses.replace(imu_profile("consumer").config, level_error_sigma_rad=0.0)
    sim = ImuSim(np.random.default_rng(3), cfg)
    twin = ImuSim(np.random.default_rng(3), cfg)
    cal = sim.level_calibration(np.random.default_rng(9))
    assert cal is not None and cal.level_error_rad == (0.0, 0.0)
    # what the part reads level, without noise: mounting, matrix and bias at switch-on
    _g, a = sim.errors.scale_matrices(cfg.temperature_at(0.0))
    _bg, ba = sim.errors.total_bias(cfg.temperature_at(0.0))
    u = np.array(a) @ LEVEL + np.array(ba)
    u /= np.linalg.norm(u)
    assert math.degrees(cal.trim.pitch_rad) == pytest.approx(math.degrees(math.asin(u[0])),
                                                             abs=0.03)
    assert math.degrees(cal.trim.roll_rad) == pytest.approx(
        math.degrees(math.atan2(-u[1], -u[2])), abs=0.03)
    assert abs(cal.trim.roll_rad) + abs(cal.trim.pitch_rad) > math.radians(0.1)
    # the flight after it draws exactly what a flight without it draws
    for k in range(300):
        assert sim.frame((0.1, 0.0, 0.2), (0.5, 0.0, -G), 2000.0) == twin.frame(
            (0.1, 0.0, 0.2), (0.5, 0.0, -G), 2000.0), k
    assert ImuSim(np.random.default_rng(3), ImuSimConfig()).level_calibration(
        np.random.default_rng(9)) is None


def test_a_lockstep_flight_flies_with_the_installations_trims(tmp_path: Path) -> None:
    from companion.core.config import Config
    from companion.sim.lockstep import run_lockstep
    from companion.sim.runner import SimOptions

    tmp = tmp_path
    cfg = Config()
    cfg.logs.dir = str(tmp / "flights")
    cfg.params.file = str(tmp / "params.parm")
    seen: dict[str, float] = {}

    def grab(rt: object) -> None:
        params = rt.ctx.params  # type: ignore[attr-defined]
        rt.manager.on_tick.append(lambda: seen.update(  # type: ignore[attr-defined]
            roll=params.get("EST_TRIM_ROLL"), pitch=params.get("EST_TRIM_PITCH")))

    summary = run_lockstep(cfg, SimOptions(scenario="level", seed=2), 5.0,
                           handle_signals=False, on_runtime=grab)
    cal = summary["simulator"]["level_calibration"]
    # float32 parameters, 4-decimal degrees in the summary
    assert math.degrees(seen["roll"]) == pytest.approx(cal["trim_roll_deg"], abs=2e-4)
    assert math.degrees(seen["pitch"]) == pytest.approx(cal["trim_pitch_deg"], abs=2e-4)
    assert abs(cal["trim_roll_deg"]) + abs(cal["trim_pitch_deg"]) > 0.05
    off = run_lockstep(cfg, SimOptions(scenario="level", seed=2, level_calibration=False), 2.0,
                       handle_signals=False)
    assert "level_calibration" not in off["simulator"]


# ----------------------------------------------------------------------- from a ground station


class StillImu(ManagedThread):
    """The IMU thread's row on a 100 Hz timer: a board tilted on a level aircraft, or shaken."""

    def __init__(self, roll_deg: float, pitch_deg: float) -> None:
        super().__init__(VEHICLE["imu"].task.replace(period_ms=10.0, budget_ms=None,
                                                     watchdog_ms=500, implementation=""))
        self.m = _board(roll_deg, pitch_deg)
        self.rng = np.random.default_rng(1)
        self.counter = 0
        self.shaking = False
        self.silent = False

    def step(self) -> bool:
        if self.silent:
            return True
        self.counter += 1
        rates = self.rng.normal(0.0, 0.3 if self.shaking else 0.002, 3)
        accel = self.m @ LEVEL + self.rng.normal(0.0, 0.02, 3)
        self.ctx.state.imu_stream.put(ImuSample(
            self.ctx.clock.monotonic_ns(), self.counter & 0xFFFF,
            tuple(rates.tolist()), tuple(accel.tolist())))  # type: ignore[arg-type]
        return True


@contextmanager
def bench_runtime(imu: StillImu, endpoint: str) -> Iterator[ParamRegistry]:
    """The real estimator thread, no GPS (a bench), the MAVLink bridge on ``endpoint``."""
    ctx = RuntimeContext(params=ParamRegistry(), home_lla=(47.0, 8.0, 500.0))
    manager = ThreadManager(ctx, [imu, EstimatorThread(task=VEHICLE["estimator"].task)])
    ctx.params.set("MGR_WDG_GRAN_MS", 10)
    bridge = MavlinkBridge(ctx, manager, [endpoint])
    manager.start()
    runner = threading.Thread(target=manager.run, daemon=True)
    runner.start()
    try:
        yield ctx.params
    finally:
        manager.request_stop("test over")
        runner.join(10.0)
        manager.shutdown()
        bridge.close()


@contextmanager
def bench_vehicle(imu: StillImu) -> Iterator[tuple[ParamRegistry, MiniGcs]]:
    """`bench_runtime` with the project's raw pymavlink client."""
    gcs = MiniGcs(listen_port=free_udp_port())
    try:
        with bench_runtime(imu, f"udpout:127.0.0.1:{gcs.port}") as params:
            assert gcs.recv(5.0, "HEARTBEAT") is not None
            yield params, gcs
    finally:
        gcs.close()


def _level_command(gcs: MiniGcs) -> tuple[object, list[str]]:
    """MAVProxy's ahrstrim (param5 = 2): the ACK and the texts after it."""
    old = {id(m) for m in gcs.history}
    gcs.send(mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_PREFLIGHT_CALIBRATION,
                                                  0, 0, 0, 0, 0, 2, 0, 0))
    ack = gcs.recv(8.0, "COMMAND_ACK",
                   lambda m: m.command == mavlink.MAV_CMD_PREFLIGHT_CALIBRATION)
    gcs.seen(2.0, "STATUSTEXT", lambda m: id(m) not in old and "calibration" in m.text)
    gcs.collect(0.2)  # the rest of a chunked text
    texts: list[str] = []
    chunks: dict[int, list[str]] = {}
    for m in gcs.history:
        if m.get_type() == "STATUSTEXT" and id(m) not in old:
            if m.id:  # MAVLink 2 chunks of a longer text, in order
                chunks.setdefault(m.id, []).append(m.text)
            else:
                texts.append(m.text)
    return ack, texts + ["".join(c) for c in chunks.values()]


def test_level_horizon_from_a_ground_station_sets_the_trims_or_says_why_not() -> None:
    imu = StillImu(1.2, -0.7)
    with bench_vehicle(imu) as (params, gcs):
        assert wait_for(lambda: imu.counter > 10, 5.0)
        ack, texts = _level_command(gcs)
        assert ack is not None and ack.result == mavlink.MAV_RESULT_ACCEPTED, (ack, texts)
        assert math.degrees(params.get("EST_TRIM_ROLL")) == pytest.approx(1.2, abs=0.05)
        assert math.degrees(params.get("EST_TRIM_PITCH")) == pytest.approx(-0.7, abs=0.05)
        assert any(re.match(r"level calibration done: roll \+1\.[12]\d pitch -0\.[67]\d deg", t)
                   for t in texts), texts
        # the aircraft picked up: refused, the trims kept
        imu.shaking = True
        ack, texts = _level_command(gcs)
        assert ack is not None and ack.result == mavlink.MAV_RESULT_FAILED, (ack, texts)
        assert any("aircraft is moving (gyro" in t for t in texts), texts
        assert math.degrees(params.get("EST_TRIM_ROLL")) == pytest.approx(1.2, abs=0.05)
        # the IMU silent: refused when the wait runs out, not left unanswered
        imu.silent = True
        ack, texts = _level_command(gcs)
        assert ack is not None and ack.result == mavlink.MAV_RESULT_FAILED, (ack, texts)
        assert any("IMU samples" in t for t in texts), texts
        # other calibrations are not this runtime's
        gcs.send(mavlink.MAVLink_command_long_message(
            1, 1, mavlink.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 1, 0, 0, 0, 0, 0, 0))
        ack = gcs.recv(3.0, "COMMAND_ACK")
        assert ack is not None and ack.result == mavlink.MAV_RESULT_UNSUPPORTED


def test_mavproxy_ahrstrim_level_calibrates(tmp_path: Path) -> None:
    """MAVProxy 1.8.75's own command, as a separate process (a PX4 identity on its link, as
    docs/ground-stations.md asks for MAVProxy)."""
    from test_gcs_mavproxy import MavProxy

    imu = StillImu(-0.9, 1.4)
    port = free_udp_port()
    with bench_runtime(imu, f"udpout:127.0.0.1:{port}?identity=px4") as params:
        mp = MavProxy(port, tmp_path, modules="param,calibration,cmdlong")
        try:
            assert mp.wait_line("Received", 25.0) is not None, "\n".join(mp.lines)
            mark = mp.mark()
            mp.cmd("ahrstrim")
            assert wait_for(lambda: abs(math.degrees(params.get("EST_TRIM_PITCH")) - 1.4) < 0.05,
                            10.0), "\n".join(mp.lines[mark:])
            assert math.degrees(params.get("EST_TRIM_ROLL")) == pytest.approx(-0.9, abs=0.05)
            line = mp.wait_line("level calibration done", 5.0, mark)
            assert line is not None, "\n".join(mp.lines[mark:])
        finally:
            mp.close()
