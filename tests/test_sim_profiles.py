"""Sensor and air profiles (companion.sim.profiles): each term comes out as specified."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.sim.campaign import CampaignError, load_campaign
from companion.sim.gps_sim import GpsSim, GpsSimConfig
from companion.sim.imu_model import ImuSimConfig, dlpf_gain
from companion.sim.imu_sim import ImuSim
from companion.sim.profiles import (
    DEG,
    GPS_PROFILES,
    IMU_PROFILES,
    TURBULENCE,
    gps_profile,
    imu_profile,
    perfect_gps,
    resolve_sensors,
)

QUIET = ImuSimConfig(gyro_noise_rad_s=0.0, accel_noise_m_s2=0.0, gyro_bias_sigma_rad_s=0.0,
                     accel_bias_sigma_m_s2=0.0, gyro_bias_walk_rad_s_sqrt_s=0.0,
                     accel_bias_walk_m_s2_sqrt_s=0.0)
"""No error at all: each test switches on the one term it checks."""
LEVEL = (0.0, 0.0, -9.80665)


def outputs(sim: ImuSim, n: int, rates: tuple[float, float, float] = (0.0, 0.0, 0.0),
            accel: tuple[float, float, float] = LEVEL, rpm: float = 0.0) -> np.ndarray:
    """The part's output (before the wire format) for ``n`` frames of constant truth."""
    out = np.empty((n, 6))
    for k in range(n):
        sim.frame(rates, accel, rpm, 25.0)
        out[k, :3] = sim.last_rates_rad_s
        out[k, 3:] = sim.last_accel_m_s2
    return out


def allan_deviation(x: np.ndarray, cluster: int) -> float:
    means = x[: len(x) // cluster * cluster].reshape(-1, cluster).mean(axis=1)
    return float(np.sqrt(0.5 * np.mean(np.diff(means) ** 2)))


def test_simple_profile_is_the_original_model() -> None:
    assert imu_profile("simple").config == ImuSimConfig()
    assert gps_profile("simple").config == GpsSimConfig()
    assert set(IMU_PROFILES) >= {"consumer", "tactical", "isis", "simple", "ideal"}
    assert set(GPS_PROFILES) >= {"ublox-m8", "dg16", "simple", "ideal"}
    assert TURBULENCE == {"none": 0, "light": 3, "moderate": 4, "severe": 6}


@pytest.mark.parametrize("name", ["consumer", "tactical"])
def test_noise_density_from_a_still_imu(name: str) -> None:
    cfg = imu_profile(name).config
    only_noise = dataclasses.replace(QUIET, gyro_noise_rad_s=cfg.gyro_noise_rad_s,
                                     accel_noise_m_s2=cfg.accel_noise_m_s2)
    out = outputs(ImuSim(np.random.default_rng(1), only_noise), 40_000)
    density = cfg.gyro_noise_rad_s / 10.0  # sigma = density * sqrt(100 Hz)
    # the Allan deviation of white noise at tau = 1 s is the noise density
    for axis in range(3):
        assert allan_deviation(out[:, axis], 100) == pytest.approx(density, rel=0.1)


def test_bias_instability_is_a_bounded_gauss_markov_process() -> None:
    sigma = 20.0 / 3600.0 * DEG
    cfg = dataclasses.replace(QUIET, gyro_bias_instability_rad_s=sigma, bias_correlation_s=10.0)
    sim = ImuSim(np.random.default_rng(2), cfg)
    out = outputs(sim, 60_000)[:, :3]
    assert np.abs(out).max() < 6 * sigma
    assert out.std() == pytest.approx(sigma, rel=0.25)
    # correlated: neighbouring samples nearly equal, samples far apart unrelated
    lag1 = np.corrcoef(out[:-1, 0], out[1:, 0])[0, 1]
    assert lag1 > 0.99


def test_scale_factor_cross_axis_and_misalignment_are_applied() -> None:
    cfg = dataclasses.replace(QUIET, gyro_scale_sigma=0.01, accel_scale_sigma=0.01)
    sim = ImuSim(np.random.default_rng(3), cfg)
    out = outputs(sim, 2, rates=(1.0, -2.0, 0.5), accel=(1.0, 2.0, -9.8))[-1]
    gs = np.array(sim.errors.gyro_scale)
    assert np.abs(gs).max() > 1e-4
    assert out[:3] == pytest.approx(np.array([1.0, -2.0, 0.5]) * (1 + gs), abs=1e-12)
    tilted = dataclasses.replace(QUIET, misalignment_sigma_rad=math.radians(1.0))
    sim = ImuSim(np.random.default_rng(3), tilted)
    out = outputs(sim, 1, accel=LEVEL)[-1]
    assert np.linalg.norm(out[3:]) == pytest.approx(9.80665)  # a rotation keeps the length
    assert np.abs(out[3:5]).max() > 0.01  # but gravity leaks into x, y


def test_clipping_at_the_configured_range_and_the_parts_lsb() -> None:
    cfg = imu_profile("consumer").config
    sim = ImuSim(np.random.default_rng(4), dataclasses.replace(
        QUIET, gyro_range_rad_s=cfg.gyro_range_rad_s, accel_range_m_s2=cfg.accel_range_m_s2,
        gyro_lsb_rad_s=cfg.gyro_lsb_rad_s, accel_lsb_m_s2=cfg.accel_lsb_m_s2))
    out = outputs(sim, 1, rates=(50.0, -50.0, 0.3), accel=(0.0, 0.0, -300.0))[-1]
    assert out[0] == pytest.approx(2000 * DEG, rel=1e-4) and out[1] == pytest.approx(-2000 * DEG,
                                                                                    rel=1e-4)
    assert out[5] == pytest.approx(-16 * 9.80665, rel=1e-4)
    steps = out[2] / cfg.gyro_lsb_rad_s
    assert steps == pytest.approx(round(steps), abs=1e-6)  # on the part's own grid


def test_vibration_peak_appears_at_the_aliased_frequency() -> None:
    cfg = dataclasses.replace(QUIET, vib_accel_m_s2=(0.0, 0.0, 2.0), vib_ref_rpm=2400.0,
                              vib_harmonics=((1.0, 1.0), (2.0, 0.6)), dlpf_hz=42.0)
    sim = ImuSim(np.random.default_rng(5), cfg)
    rpm = 2100.0  # shaft 35 Hz; blade pass 70 Hz aliases to 30 Hz at 100 Hz sampling
    z = outputs(sim, 4000, rpm=rpm)[:, 5] + 9.80665
    spectrum = np.abs(np.fft.rfft(z)) / len(z) * 2
    freqs = np.fft.rfftfreq(len(z), 0.01)
    peaks = sorted(freqs[np.argsort(spectrum)[-2:]])
    assert peaks == pytest.approx([30.0, 35.0], abs=0.05)
    load = (rpm / 2400.0) ** 2
    assert spectrum[np.argmin(np.abs(freqs - 35.0))] == pytest.approx(
        2.0 * load * dlpf_gain(35.0, 42.0), rel=0.02)
    assert spectrum[np.argmin(np.abs(freqs - 30.0))] == pytest.approx(
        1.2 * load * dlpf_gain(70.0, 42.0), rel=0.02)
    still = outputs(ImuSim(np.random.default_rng(5), cfg), 10, rpm=0.0)[:, 5]
    assert still == pytest.approx(-9.80665)  # engine stopped: no vibration


def test_temperature_warms_and_moves_the_bias() -> None:
    cfg = imu_profile("consumer").config
    assert cfg.temperature_at(0.0) == pytest.approx(20.0)
    assert cfg.temperature_at(cfg.temperature_tau_s) == pytest.approx(40.0 - 20.0 / math.e)
    drift = dataclasses.replace(QUIET, gyro_bias_temp_rad_s_per_c=0.001)
    sim = ImuSim(np.random.default_rng(6), drift)
    sim.frame((0, 0, 0), LEVEL, 0.0, 25.0)
    assert sim.last_rates_rad_s == pytest.approx([0, 0, 0], abs=1e-15)
    sim.frame((0, 0, 0), LEVEL, 0.0, 35.0)
    assert sim.last_rates_rad_s == pytest.approx(10.0 * np.array(sim.errors.gyro_bias_temp))
    assert sim.gyro_bias_rad_s == pytest.approx(10.0 * np.array(sim.errors.gyro_bias_temp))


@pytest.mark.parametrize("name", list(IMU_PROFILES))
def test_every_imu_profile_is_deterministic(name: str) -> None:
    cfg = imu_profile(name).config

    def stream(seed: int) -> bytes:
        sim = ImuSim(np.random.default_rng(seed), cfg)
        return b"".join(sim.frame((0.1, 0.2, 0.3), (0.5, 0.1, -9.8), 2300.0 + k,
                                  sim.temperature_at(k / 100)) for k in range(300))

    assert stream(7) == stream(7)
    if name != "ideal":
        assert stream(7) != stream(8)


def test_gps_latency_mean_and_jitter() -> None:
    cfg = gps_profile("ublox-m8").config
    sim = GpsSim(np.random.default_rng(8), cfg)
    latencies = []
    for k in range(3000):
        sim.epoch(3600.0 + k / 10, 45.0, 9.0, 300.0, 20.0, 0.0, 0.0)
        latencies.append(sim.last_latency_s)
    assert np.mean(latencies) == pytest.approx(cfg.latency_s, abs=0.002)
    assert np.std(latencies) == pytest.approx(cfg.latency_jitter_s, rel=0.1)
    assert min(latencies) >= 0.0


def test_gps_outages_give_no_fix_epochs() -> None:
    cfg = dataclasses.replace(gps_profile("dg16").config, outage_per_h=120.0, outage_s=5.0)
    sim = GpsSim(np.random.default_rng(9), cfg)
    fixes = []
    for k in range(36_000):  # one hour at 10 Hz
        sim.epoch(3600.0 + k / 10, 45.0, 9.0, 300.0, 20.0, 0.0, 0.0)
        assert sim.last_solution is not None
        fixes.append(sim.last_solution.fix)
        if sim.in_outage:
            assert sim.last_solution.lat_deg is None
    lost = fixes.count(0)
    assert 60 <= sim.outages <= 180
    assert lost == pytest.approx(sim.outages * 50, rel=0.05)  # 5 s of 10 Hz epochs each


def test_gps_correlated_error_and_multipath() -> None:
    cfg = gps_profile("ublox-m8").config
    sim = GpsSim(np.random.default_rng(10), dataclasses.replace(cfg, outage_per_h=0.0))
    errors = []
    for k in range(20_000):
        sim.epoch(3600.0 + k / 10, 45.0, 9.0, 300.0, 20.0, 0.0, 0.0)
        errors.append(sim.last_error_ned_m)
    err = np.array(errors)
    lag1 = np.corrcoef(err[:-1, 0], err[1:, 0])[0, 1]
    assert lag1 > 0.8  # dominated by the slowly varying part, not white
    assert np.abs(err[:, :2]).max() < 8 * math.hypot(cfg.gm_horiz_m, cfg.horiz_white_m)


def test_dual_antenna_heading_noise_mounting_and_no_effect_on_other_receivers() -> None:
    cfg = gps_profile("dual-antenna").config
    assert "HDT" in cfg.sentences and cfg.heading_std_deg > 0.0
    sim = GpsSim(np.random.default_rng(11), cfg)
    errors = []
    for k in range(3000):
        data = sim.epoch(3600.0 + k / 10, 45.0, 9.0, 300.0, 20.0, 0.0, 0.0, 359.9)
        assert b"HDT," in data
        sol = sim.last_solution
        assert sol is not None
        if sol.fix:
            assert sol.heading_deg is not None and 0.0 <= sol.heading_deg < 360.0
            errors.append((sol.heading_deg - 359.9 + 180.0) % 360.0 - 180.0)
    err = np.array(errors)
    assert abs(sim.heading_mount_deg) > 0.0  # drawn once per receiver
    assert float(np.mean(err)) == pytest.approx(sim.heading_mount_deg, abs=0.03)
    assert float(np.std(err)) == pytest.approx(cfg.heading_std_deg, rel=0.1)
    # the heading's draws are a stream of their own: the position errors are the M8's
    m8 = GpsSim(np.random.default_rng(11), gps_profile("ublox-m8").config)
    dual = GpsSim(np.random.default_rng(11), cfg)
    for k in range(200):
        a = m8.epoch(3600.0 + k / 10, 45.0, 9.0, 300.0, 20.0, 0.0, 0.0, 90.0)
        b = dual.epoch(3600.0 + k / 10, 45.0, 9.0, 300.0, 20.0, 0.0, 0.0, 90.0)
        assert b.startswith(a) and b"HDT," not in a
    assert perfect_gps(cfg).heading_std_deg == 0.0 and perfect_gps(cfg).perfect


def test_gps_rate_must_divide_the_tick() -> None:
    for rate in (1.0, 5.0, 10.0):
        GpsSimConfig(rate_hz=rate)
    with pytest.raises(ValueError, match="rate_hz"):
        GpsSimConfig(rate_hz=3.0)


@pytest.mark.parametrize("rate_hz", [1.0, 5.0, 10.0])
def test_recorded_flight_gets_epochs_at_the_profile_rate(rate_hz: float) -> None:
    from companion.evaluation.sitl import FlightSpec, record_flight

    rec = record_flight(FlightSpec(scenario="level", seed=2, duration_s=4.0,
                                   gps=dataclasses.replace(gps_profile("ublox-m8").config,
                                                           rate_hz=rate_hz, outage_per_h=0.0)))
    assert len(rec.gps_epoch_t_s) == int(4 * rate_hz)
    assert np.diff(rec.gps_epoch_t_s) == pytest.approx(np.full(len(rec.gps_epoch_t_s) - 1,
                                                               1.0 / rate_hz))
    assert rec.gps_latency_true_s.mean() == pytest.approx(0.1, abs=0.03)
    assert rec.sensors["imu_profile"] == "consumer" and rec.sensors["turbulence"] == "moderate"
    assert rec.propeller_rpm.min() > 1000 and rec.imu_temperature_c[0] == pytest.approx(20, abs=1)
    assert np.abs(rec.imu_gyro_scale).max() > 0 and np.abs(rec.imu_misalignment_rad).max() > 0


def test_no_noise_makes_every_sensor_perfect() -> None:
    setup = resolve_sensors(no_noise=True)
    assert setup.imu == imu_profile("ideal").config
    assert setup.gps.perfect and setup.gps.rate_hz == gps_profile("ublox-m8").config.rate_hz
    assert setup.turbulence == "none"
    assert resolve_sensors(no_noise=True, turbulence="severe").turbulence_severity == 6
    default = resolve_sensors()
    assert (default.imu_profile, default.gps_profile, default.turbulence) == (
        "consumer", "ublox-m8", "moderate")
    assert resolve_sensors(gps_latency_s=0.2).gps.latency_s == 0.2
    sim = GpsSim(np.random.default_rng(11), setup.gps)
    for k in range(50):
        sim.epoch(3600.0 + k / 10, 45.0, 9.0, 300.0, 20.0, 1.0, 0.0)
        assert sim.last_error_ned_m == (0.0, 0.0, 0.0)
        assert sim.last_latency_s == setup.gps.latency_s and not sim.in_outage


def test_bad_names_list_the_choices(tmp_path: Path) -> None:
    for call, bad in ((imu_profile, "mpu"), (gps_profile, "garmin")):
        with pytest.raises(ValueError, match="choose one of") as info:
            call(bad)
        assert bad in str(info.value)
    with pytest.raises(ValueError, match="none, light, moderate, severe"):
        resolve_sensors(turbulence="stormy")
    spec = tmp_path / "c.toml"
    spec.write_text('imu_profile = "nope"\n[grid]\nseed = [1]\n', encoding="utf-8")
    with pytest.raises(CampaignError, match="consumer, tactical"):
        load_campaign(spec)
    spec.write_text('imu_profile = "tactical"\nturbulence = "light"\n[grid]\nseed = [1]\n',
                    encoding="utf-8")
    assert load_campaign(spec)[0].settings["imu_profile"] == "tactical"


def test_cli_flags_parse_and_refuse_bad_names() -> None:
    from companion.cli import build_parser

    args = build_parser().parse_args(["sim", "--imu-profile", "tactical", "--gps-profile",
                                      "dg16", "--turbulence", "severe", "--gps-latency", "0.2"])
    assert (args.imu_profile, args.gps_profile, args.turbulence, args.gps_latency) == (
        "tactical", "dg16", "severe", 0.2)
    done = subprocess.run([sys.executable, "-m", "companion", "sim", "--imu-profile", "bogus",
                           "--duration", "1"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert "bogus" in done.stderr and "consumer, tactical, isis, simple, ideal" in done.stderr
    assert "Traceback" not in done.stderr
