"""What limits the GPS/INS estimator's inclination accuracy in SITL: an error budget.

    .venv/bin/python bench/estimation_budget_bench.py             # 5 seeds x 21 worlds (~2-4 min)
    .venv/bin/python bench/estimation_budget_bench.py --seeds 2   # a quick look

The accuracy bench (``estimation_sitl_bench.py``) says how far the estimator is from its
targets; this one says why. It flies the same kind of flight as that bench's accuracy study
(c172p, ``turns``, 8 m/s wind from the west, 120 s, scored from 30 s, GPS latency 0.15 s the
filter is not told, the estimator with its thread's defaults) in worlds that each remove one
group of errors, and prints every world's inclination figures against the default world
flown on the same seeds in the same run. An error source whose removal changes little is not
what holds the figure up; a group whose removal halves it is.

Removing a group keeps every random draw in place (its sizes become 1e-12, not 0), so a seed
flies the same pilot, turbulence and remaining sensor errors in every world. The groups follow
``companion.sim.imu_model.ImuSimConfig``:

* calibration: scale factors, cross-axis terms, mounting misalignment, g-sensitivity and the
  scale factors' temperature drift, gyro and accelerometer;
* bias dynamics: bias temperature drift (the warm-up), bias instability, bias random walk;
* turn-on biases;
* noise: white noise and engine vibration.

The last worlds add instead of remove: the default world with the estimator given a heading
fix of the airframe (truth plus noise, with or without a constant error) with each GPS fix.
No simulated sensor provides one; they say what a heading reference would buy, and how
unbiased it must be, since in a steady turn a heading error becomes a tilt error.

This is the project's own simulator and its own assumed error sizes (docs/sitl.md): the
figures rank the error sources of that model, not of a real aircraft.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import multiprocessing as mp
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from companion.sim.profiles import (  # noqa: E402
    DEFAULT_IMU_PROFILE,
    imu_profile,
)

OFF = 1e-12
"""An error size that keeps its random draw but removes its effect."""

CALIBRATION = dict(gyro_scale_sigma=OFF, gyro_cross_axis_sigma=OFF, accel_scale_sigma=OFF,
                   accel_cross_axis_sigma=OFF, misalignment_sigma_rad=OFF,
                   gyro_g_sensitivity_rad_s_per_m_s2=OFF, gyro_scale_temp_per_c=OFF,
                   accel_scale_temp_per_c=OFF)
BIAS_DYNAMICS = dict(gyro_bias_temp_rad_s_per_c=OFF, accel_bias_temp_m_s2_per_c=OFF,
                     gyro_bias_instability_rad_s=OFF, accel_bias_instability_m_s2=OFF,
                     gyro_bias_walk_rad_s_sqrt_s=OFF, accel_bias_walk_m_s2_sqrt_s=OFF)
TURN_ON = dict(gyro_bias_sigma_rad_s=OFF, accel_bias_sigma_m_s2=OFF)
NOISE = dict(gyro_noise_rad_s=OFF, accel_noise_m_s2=OFF, vib_accel_m_s2=(0.0, 0.0, 0.0),
             vib_gyro_rad_s=(0.0, 0.0, 0.0))
LAG_TOLD = {"GPS_LAG": 0.15, "GPS_LAGSD": 0.0}

WORLDS: dict[str, tuple[str, dict[str, Any], dict[str, Any], dict[str, float]]] = {
    # name: (what it is, FlightSpec fields, IMU error overrides, estimator parameters)
    "default": ("the accuracy bench's world", {}, {}, {}),
    "lag told": ("the filter is told the 0.15 s GPS latency", {}, {}, LAG_TOLD),
    "still air": ("no turbulence", {"turbulence": "none"}, {}, {}),
    "perfect GPS": ("no GPS error, jitter, multipath or outage (same latency)",
                    {"gps_profile": "ideal"}, {}, {}),
    "no IMU noise": ("IMU white noise and vibration removed", {}, NOISE, {}),
    "no gyro matrix": ("gyro scale factors and cross-axis terms removed", {},
                       dict(gyro_scale_sigma=OFF, gyro_cross_axis_sigma=OFF,
                            gyro_scale_temp_per_c=OFF), {}),
    "no accel matrix": ("accelerometer scale factors and cross-axis terms removed", {},
                        dict(accel_scale_sigma=OFF, accel_cross_axis_sigma=OFF,
                             accel_scale_temp_per_c=OFF), {}),
    "no gyro warm-up": ("the gyro biases' temperature drift removed (what a perfect model of "
                        "the warm-up could buy)", {},
                        dict(gyro_bias_temp_rad_s_per_c=OFF), {}),
    "no misalignment": ("mounting misalignment (0.5 deg before the level calibration) removed",
                        {}, dict(misalignment_sigma_rad=OFF), {}),
    "level exactly": ("the aircraft stood exactly level for the level calibration (0.1 deg)",
                      {}, dict(level_error_sigma_rad=OFF), {}),
    "bias kept in trim": ("the filter does not give back the bias the calibration took "
                          "(EST_TRIM_BIAS 0)", {}, {}, {"TRIM_BIAS": 0.0}),
    "no level calibration": ("the installation flies without trims (--no-level-cal)",
                             {"level_calibration": False}, {}, {}),
    "no IMU calibration": ("IMU scale, cross-axis, misalignment, g-sensitivity removed", {},
                           CALIBRATION, {}),
    "+ no bias dynamics": ("... and bias warm-up, instability and walk", {},
                           {**CALIBRATION, **BIAS_DYNAMICS}, {}),
    "+ no turn-on bias": ("... and the turn-on biases", {},
                          {**CALIBRATION, **BIAS_DYNAMICS, **TURN_ON}, {}),
    "tactical IMU": ("the `tactical` profile instead of `consumer`",
                     {"imu_profile": "tactical"}, {}, {}),
    "perfect IMU": ("the `ideal` profile (the wire format's quantisation only)",
                    {"imu_profile": "ideal"}, {}, {}),
    "perfect world": ("ideal IMU and GPS, still air, latency told",
                      {"imu_profile": "ideal", "gps_profile": "ideal", "turbulence": "none"},
                      {}, LAG_TOLD),
}
"""Each world: what it removes, FlightSpec fields, IMU error sizes, estimator parameters."""

AIDED: dict[str, tuple[str, dict[str, float]]] = {
    "+ heading fix 1 deg": ("nothing; a heading fix of the airframe is added with each GPS fix, "
                            "1 deg 1-sigma white noise (no simulated sensor gives one)",
                            {"heading_std_rad": math.radians(1.0)}),
    "+ heading fix 0.5 deg off": ("the same fix with a constant 0.5 deg error (a heading "
                                  "sensor's bias or mounting error)",
                                  {"heading_std_rad": math.radians(1.0),
                                   "heading_bias_rad": math.radians(0.5)}),
    "+ heading fix 2 deg off": ("the same fix with a constant 2 deg error",
                                {"heading_std_rad": math.radians(1.0),
                                 "heading_bias_rad": math.radians(2.0)}),
}
"""Worlds flown as the default one, with the estimator given a heading reference: what the
default world lacks (`EskfOptions.heading_std_rad`)."""

WARMUP_S = 30.0


def fly(job: tuple[str, int, float]) -> tuple[str, int, dict[str, float]]:
    world, seed, duration_s = job
    from companion.evaluation.sitl import FlightSpec
    from companion.evaluation.sitl_benchmark import evaluate
    from companion.evaluation.sitl_estimator import EskfOptions

    aided: dict[str, float] = {}
    if world in AIDED:
        _, spec_fields, imu_over, params = WORLDS["default"]
        aided = AIDED[world][1]
    else:
        _, spec_fields, imu_over, params = WORLDS[world]
    imu = None
    if imu_over:
        imu = dataclasses.replace(imu_profile(DEFAULT_IMU_PROFILE).config, **imu_over)
    spec = FlightSpec(aircraft="c172p", scenario="turns", seed=seed, duration_s=duration_s,
                      gps_latency_s=0.15, wind_ned_m_s=(0.0, 8.0, 0.0), imu=imu, **spec_fields)
    res = evaluate(spec, {"eskf": EskfOptions(params=params, **aided)}, imu_only=())
    err = np.degrees(np.asarray(res.errors["eskf"].inclination_rad, dtype=float))
    keep = (res.t_s >= WARMUP_S) & np.isfinite(err)
    e = err[keep]
    return world, seed, {"rmse": float(np.sqrt(np.mean(e**2))),
                         "p95": float(np.percentile(e, 95)), "max": float(e.max())}


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5, help="seeds 0..N-1 (5 at most stays clear of the tuning seeds "
                         "5-20, 101 and 102)")
    ap.add_argument("--duration-s", type=float, default=120.0)
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    args = ap.parse_args(argv)
    if args.seeds < 1 or args.duration_s <= WARMUP_S + 10.0:
        ap.error("need --seeds >= 1 and --duration-s > 40")
    names = [*WORLDS, *AIDED]
    jobs = [(w, s, args.duration_s) for w in names for s in range(args.seeds)]
    t0 = time.monotonic()
    figures: dict[str, dict[int, dict[str, float]]] = {w: {} for w in names}
    with ProcessPoolExecutor(args.jobs, mp_context=mp.get_context("fork")) as ex:
        for world, seed, fig in ex.map(fly, jobs):
            figures[world][seed] = fig
    load = os.getloadavg()[0]
    print(f"## Error budget: c172p, turns, 8 m/s wind, {args.duration_s:.0f} s, scored from "
          f"{WARMUP_S:.0f} s, seeds 0-{args.seeds - 1} ({len(jobs)} flights, "
          f"{time.monotonic() - t0:.0f} s, load {load:.2f})\n")
    print("| world | what is removed | inclination RMSE, deg (mean of seeds) | ratio to default "
          "| p95 | max | per seed |")
    print("|---|---|---|---|---|---|---|")
    base = float(np.mean([f["rmse"] for f in figures["default"].values()]))
    descriptions = {**{w: v[0] for w, v in WORLDS.items()}, **{w: v[0] for w, v in AIDED.items()}}
    for world, what in descriptions.items():
        per = [figures[world][s] for s in range(args.seeds)]
        rmse = float(np.mean([f["rmse"] for f in per]))
        p95 = float(np.mean([f["p95"] for f in per]))
        worst = max(f["max"] for f in per)
        seeds = " ".join(f"{f['rmse']:.2f}" for f in per)
        ratio = rmse / base if base > 0 and math.isfinite(base) else math.nan
        print(f"| {world} | {what} | {rmse:.3f} | {ratio:.2f} | {p95:.2f} | {worst:.2f} "
              f"| {seeds} |")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.result import run_captured

    sys.exit(run_captured("estimation_budget", ["companion/estimation", "companion/evaluation", "companion/sim"], lambda: main(sys.argv[1:])))
