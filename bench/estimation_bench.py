"""Estimation bench on synthetic data: accuracy and per-step cost of both filters.

    .venv/bin/python bench/estimation_bench.py --quick      # ~1 min on the 2-core machine
    .venv/bin/python bench/estimation_bench.py --full       # ~5 min
    .venv/bin/python bench/estimation_bench.py --quick --json out.json

Attitude: hand-held style recordings (rest, fast rotation, translation; the kind of motion the
published 6-D filter benchmarks use) with MEMS-like errors (bias, bias drift, scale factor,
noise, vibration), scored by the inclination RMSE. If the ``vqf`` package is installed its
default 6-D output is scored on the same data for comparison (not a dependency of the
project: ``pip install vqf`` for the comparison only).

ESKF: a fixed-wing flight (level, 30 deg coordinated turns, climbs) with 10 Hz GPS arriving
0.15 s late, scored by inclination, heading, velocity and position RMSE, plus the median and
99th percentile cost of ``predict`` and ``update_gps``. The SITL-driven comparison comes later.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from companion.estimation.attitude import AttitudeFilter  # noqa: E402
from companion.estimation.eskf import Eskf  # noqa: E402
from companion.estimation.quat import (  # noqa: E402
    heading_error_rad,
    inclination_error_rad,
    quat_to_rotmat,
)
from companion.evaluation.synthetic import (  # noqa: E402
    ImuErrors,
    Segment,
    add_imu_errors,
    fixed_wing_flight,
    gps_fixes,
    handheld_motion,
)

# Sensor variety for the attitude trials: (rate Hz, gyro noise deg/s/rtHz, vibration m/s^2)
_TRIAL_SENSORS = [(100, 0.01, 0.05), (200, 0.01, 0.1), (100, 0.03, 0.3), (200, 0.005, 0.05), (50, 0.02, 0.02), (100, 0.01, 0.2)]


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def _vqf_inclination_deg(gyro: np.ndarray, accel: np.ndarray, rate_hz: float, q_true: np.ndarray) -> np.ndarray | None:
    try:
        from vqf import VQF  # type: ignore[import-not-found]
    except ImportError:
        return None
    filt = VQF(1.0 / rate_hz)
    q = filt.updateBatch(np.ascontiguousarray(gyro), np.ascontiguousarray(accel))["quat6D"]
    # VQF's earth frame is z-up: compare its "up" with the truth's "down", both seen in body
    up_body = quat_to_rotmat(q)[:, 2, :]
    down_body = quat_to_rotmat(q_true)[:, 2, :]
    cos_a = np.clip(np.sum(-up_body * down_body, axis=1), -1.0, 1.0)
    return np.degrees(np.arccos(cos_a))


def bench_attitude(trials: int, duration_s: float) -> dict[str, Any]:
    ours, theirs, costs = [], [], []
    for i in range(trials):
        rate, noise_deg, vib = _TRIAL_SENSORS[i % len(_TRIAL_SENSORS)]
        tr = handheld_motion(duration_s, rate_hz=rate, seed=500 + i)
        errors = ImuErrors(
            gyro_noise_rad_s_rt_hz=math.radians(noise_deg),
            gyro_bias_rad_s=math.radians(0.4),
            gyro_bias_rw_rad_s_rt_s=math.radians(0.002),
            gyro_scale=0.005,
            accel_scale=0.003,
            accel_bias_m_s2=0.08,
            vibration_m_s2=vib,
            seed=50 + i,
        )
        imu = add_imu_errors(tr, errors)
        filt = AttitudeFilter()
        dt = 1.0 / rate
        q = np.empty((len(tr.t_s), 4))
        gyro, accel = imu.gyro_rad_s.tolist(), imu.accel_m_s2.tolist()
        step_ns = np.empty(len(tr.t_s))
        for k in range(len(tr.t_s)):
            t0 = time.perf_counter_ns()
            q[k] = filt.update(gyro[k], accel[k], dt)
            step_ns[k] = time.perf_counter_ns() - t0
        costs.append(step_ns)
        ours.append(_rms(np.degrees(inclination_error_rad(q, tr.quat))))
        vqf_err = _vqf_inclination_deg(imu.gyro_rad_s, imu.accel_m_s2, rate, tr.quat)
        if vqf_err is not None:
            theirs.append(_rms(vqf_err))
    all_costs = np.concatenate(costs) / 1e3
    out: dict[str, Any] = {
        "trials": trials,
        "duration_s": duration_s,
        "inclination_rmse_deg": ours,
        "inclination_rmse_deg_mean": float(np.mean(ours)),
        "step_us_median": float(np.median(all_costs)),
        "step_us_p99": float(np.percentile(all_costs, 99)),
    }
    if theirs:
        out["vqf_inclination_rmse_deg"] = theirs
        out["vqf_inclination_rmse_deg_mean"] = float(np.mean(theirs))
        out["improvement_vs_vqf"] = 1.0 - out["inclination_rmse_deg_mean"] / out["vqf_inclination_rmse_deg_mean"]
    return out


def _flight_segments(duration_s: float) -> list[Segment]:
    pattern = [
        Segment(20.0),
        Segment(40.0, bank_deg=30.0),
        Segment(20.0, gamma_deg=6.0),
        Segment(40.0, bank_deg=-30.0),
        Segment(20.0, gamma_deg=-5.0, speed_m_s=24.0),
        Segment(30.0, bank_deg=20.0),
    ]
    segments: list[Segment] = []
    total = 0.0
    while total < duration_s:
        seg = pattern[len(segments) % len(pattern)]
        segments.append(seg)
        total += seg.duration_s
    return segments


def bench_eskf(duration_s: float, seeds: int) -> dict[str, Any]:
    rows: dict[str, list[float]] = {k: [] for k in ("incl", "heading", "vel", "pos")}
    predict_ns: list[float] = []
    update_ns: list[float] = []
    faults = 0
    nis: list[float] = []
    for seed in range(seeds):
        tr = fixed_wing_flight(_flight_segments(duration_s), heading0_rad=0.7 * seed)
        imu = add_imu_errors(
            tr,
            ImuErrors(
                gyro_noise_rad_s_rt_hz=0.003,
                accel_noise_m_s2_rt_hz=0.05,
                gyro_bias_rad_s=math.radians(0.5),
                gyro_bias_rw_rad_s_rt_s=5e-5,
                accel_bias_m_s2=0.1,
                accel_bias_rw_m_s2_rt_s=1e-3,
                gyro_scale=0.002,
                vibration_m_s2=0.2,
                seed=seed,
            ),
        )
        gps = gps_fixes(tr, rate_hz=10.0, latency_s=0.15, seed=100 + seed)
        f = Eskf()
        f.initialise(imu.accel_m_s2[0], np.zeros(3), gps.pos_ned_m[0], gps.vel_ned_m_s[0])
        gyro, accel = imu.gyro_rad_s.tolist(), imu.accel_m_s2.tolist()
        dt = 1.0 / tr.rate_hz
        gi = 1
        err = np.empty((len(tr.t_s) - 1, 4))
        for k in range(1, len(tr.t_s)):
            t0 = time.perf_counter_ns()
            f.predict(gyro[k], accel[k], dt)
            predict_ns.append(time.perf_counter_ns() - t0)
            now = float(tr.t_s[k])
            while gi < len(gps.t_report_s) and gps.t_report_s[gi] <= now + 1e-9:
                t0 = time.perf_counter_ns()
                res = f.update_gps(
                    gps.pos_ned_m[gi], gps.vel_ned_m_s[gi], gps.pos_std_m, gps.vel_std_m_s,
                    latency_s=now - float(gps.t_valid_s[gi]),
                )
                update_ns.append(time.perf_counter_ns() - t0)
                if now > 20.0 and math.isfinite(res.nis):
                    nis.append(res.nis)
                gi += 1
            s = f.state()
            err[k - 1] = (
                float(inclination_error_rad(s.quaternion, tr.quat[k])),
                float(heading_error_rad(s.quaternion, tr.quat[k])),
                float(np.linalg.norm(s.vel_ned_m_s - tr.vel_ned_m_s[k])),
                float(np.linalg.norm(s.pos_ned_m - tr.pos_ned_m[k])),
            )
        settled = tr.t_s[1:] > 20.0
        rows["incl"].append(_rms(np.degrees(err[settled, 0])))
        rows["heading"].append(_rms(np.degrees(err[settled, 1])))
        rows["vel"].append(_rms(err[settled, 2]))
        rows["pos"].append(_rms(err[settled, 3]))
        faults += f.faults
    p = np.array(predict_ns) / 1e3
    u = np.array(update_ns) / 1e3
    return {
        "flights": seeds,
        "duration_s": duration_s,
        "inclination_rmse_deg": float(np.mean(rows["incl"])),
        "heading_rmse_deg": float(np.mean(rows["heading"])),
        "velocity_rmse_m_s": float(np.mean(rows["vel"])),
        "position_rmse_m": float(np.mean(rows["pos"])),
        "mean_gps_nis_6dof": float(np.mean(nis)) if nis else math.nan,
        "faults": faults,
        "predict_us_median": float(np.median(p)),
        "predict_us_p99": float(np.percentile(p, 99)),
        "update_gps_us_median": float(np.median(u)),
        "update_gps_us_p99": float(np.percentile(u, 99)),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help="short run (default)")
    mode.add_argument("--full", action="store_true", help="longer, more trials")
    parser.add_argument("--trials", type=int, help="attitude trials (overrides the mode)")
    parser.add_argument("--duration-s", type=float, help="length of each recording (overrides the mode)")
    parser.add_argument("--json", type=Path, help="also write the figures to this file")
    args = parser.parse_args(argv)
    trials = args.trials or (12 if args.full else 4)
    duration = args.duration_s or (120.0 if args.full else 60.0)
    flights = 3 if args.full else 1
    flight_s = args.duration_s or (300.0 if args.full else 120.0)

    att = bench_attitude(trials, duration)
    print(f"attitude (6-D), {trials} hand-held recordings of {duration:.0f} s")
    print(f"  inclination RMSE      {att['inclination_rmse_deg_mean']:.3f} deg  per trial "
          + " ".join(f"{x:.2f}" for x in att["inclination_rmse_deg"]))
    if "vqf_inclination_rmse_deg_mean" in att:
        print(f"  VQF 6-D (defaults)    {att['vqf_inclination_rmse_deg_mean']:.3f} deg  per trial "
              + " ".join(f"{x:.2f}" for x in att["vqf_inclination_rmse_deg"]))
        print(f"  improvement vs VQF    {100.0 * att['improvement_vs_vqf']:.1f} %")
    else:
        print("  (vqf not installed: no comparison)")
    print(f"  step cost             median {att['step_us_median']:.0f} us, p99 {att['step_us_p99']:.0f} us")

    esk = bench_eskf(flight_s, flights)
    print(f"ESKF, {flights} fixed-wing flight(s) of {flight_s:.0f} s, GPS 10 Hz 0.15 s late")
    print("  told what a flight would not tell it: each fix's exact age, the GPS error's exact std, "
          "and IMU noise densities and bias walks equal to its defaults")
    print(f"  inclination RMSE      {esk['inclination_rmse_deg']:.3f} deg")
    print(f"  heading RMSE          {esk['heading_rmse_deg']:.3f} deg")
    print(f"  velocity RMSE         {esk['velocity_rmse_m_s']:.3f} m/s")
    print(f"  position RMSE         {esk['position_rmse_m']:.3f} m")
    print(f"  mean GPS NIS (6 dof)  {esk['mean_gps_nis_6dof']:.2f}   faults {esk['faults']}")
    print(f"  predict cost          median {esk['predict_us_median']:.0f} us, p99 {esk['predict_us_p99']:.0f} us")
    print(f"  update_gps cost       median {esk['update_gps_us_median']:.0f} us, p99 {esk['update_gps_us_p99']:.0f} us")
    if args.json:
        args.json.write_text(json.dumps({"attitude": att, "eskf": esk}, indent=2))
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.result import run_captured

    sys.exit(run_captured("estimation", ["companion/estimation", "companion/evaluation"], main))
