"""IMU-only attitude on real recordings: our filter against VQF, Madgwick and an XSENS unit.

    python bench/real_imu_bench.py            # every recording of the subset, about 1 min
    python bench/real_imu_bench.py --quick    # the held-out MPU9150 recordings only

Reads only the committed subset ``tests/data/imu-truth/leiria/`` (IMUs on an ABB robot arm,
the robot's orientation as truth) and ``tests/data/px4-ulog/sample.ulg`` (a PX4 flight, EKF2's
attitude as a reference). The procedure is ``companion/evaluation/realdata.py``'s: every filter
gets the same samples (resampled onto a uniform 100 Hz grid), one alignment per recording
fitted from the raw gyro and the truth only, inclination error from a fixed start (after the
robot's start-up glitches). "ours (t_s)" is our filter on the raw irregular samples with their
time stamps, same alignment. The XSENS MTi-30's own output has no raw samples to fit a
mounting from, so its mounting is fitted to its own output (which favours it).

The "rest oracle" row is a diagnostic, not a filter: it knows the true vertical whenever the
arm is still and integrates the gyro in between, so it shows how much of every filter's error
is the truth's own noise during motion (report timing) rather than the filter's.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from companion.estimation.quat import quat_from_rotvec, quat_to_rotmat  # noqa: E402
from companion.evaluation import realdata as rd  # noqa: E402
from companion.evaluation import realdata_scoring as rs  # noqa: E402

FILTERS = ("ours", "vqf", "madgwick")
COLUMNS = (*FILTERS, "ours_timed")
LABEL = {"ours": "ours", "vqf": "VQF", "madgwick": "Madgwick", "ours_timed": "ours (t_s)",
         "oracle": "rest oracle", "xsens": "XSENS MTi-30"}


def rest_oracle_rmse_deg(name: str) -> float:
    """Inclination RMSE of the diagnostic: true vertical while still, gyro integration between."""
    raw = rd.load_leiria(name)
    align = rd.fit_alignment(raw)
    skip = max(raw.score_from_s, rd.consistent_from_s(raw, align))
    uni = rd.resample_uniform(raw)
    up = rd.true_up_sensor(uni, align)
    rate_deg_s = np.degrees(np.linalg.norm(uni.gyro_rad_s, axis=1))
    still = np.convolve(rate_deg_s, np.ones(20) / 20, mode="same") < 1.0
    dt = float(np.median(np.diff(uni.t_s)))
    est = np.empty_like(up)
    cur = up[0].copy()
    for k in range(len(up)):
        if still[k]:
            cur = up[k].copy()
        else:
            cur = quat_to_rotmat(quat_from_rotvec(uni.gyro_rad_s[k] * dt)).T @ cur
        est[k] = cur
    err = np.degrees(rd.angle_between_rad(est, up))[uni.t_s - uni.t_s[0] >= skip]
    return float(np.sqrt(np.mean(err**2)))


def _fmt(x: float) -> str:
    return f"{x:.2f}"


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="held-out MPU9150 recordings only")
    args = ap.parse_args(argv)
    names = rd.list_leiria()
    if args.quick:
        names = [n for n in names if n.endswith("_MPU9150") and rd.load_leiria(n).held_out]
    t0 = time.monotonic()
    results = rs.score_leiria(names, FILTERS, with_timed=True)
    oracle = {r.name: rest_oracle_rmse_deg(r.name) for r in results}
    print(f"## Leiria robot arm: inclination RMSE per recording, degrees ({len(results)} "
          f"recordings, {time.monotonic() - t0:.0f} s)\n")
    print("| recording | split | " + " | ".join(LABEL[c] for c in COLUMNS)
          + " | rest oracle | ours / VQF |")
    print("| --- | --- | " + " | ".join("---:" for _ in COLUMNS) + " | ---: | ---: |")
    for r in results:
        cells = [_fmt(r.scores[c].rmse_deg) for c in COLUMNS]
        ratio = r.scores["ours"].rmse_deg / r.scores["vqf"].rmse_deg
        split = "held out" if r.held_out else "tuning"
        print(f"| {r.name} | {split} | " + " | ".join(cells)
              + f" | {_fmt(oracle[r.name])} | {ratio:.2f} |")

    print("\n## Summary: mean over recordings of the inclination RMSE (and of p95, max), "
          "degrees\n")
    print("| split | recordings | filter | mean RMSE | mean p95 | max | ratio to VQF |")
    print("| --- | ---: | --- | ---: | ---: | ---: | ---: |")
    splits = {
        "tuning": [r for r in results if not r.held_out],
        "held out": [r for r in results if r.held_out],
        "all": results,
    }
    for split, rows in splits.items():
        if not rows:
            continue
        vqf = rs.mean_rmse_deg(rows, "vqf")
        for c in COLUMNS:
            mean = rs.mean_rmse_deg(rows, c)
            p95 = float(np.mean([r.scores[c].p95_deg for r in rows]))
            worst = max(r.scores[c].max_deg for r in rows)
            print(f"| {split} | {len(rows)} | {LABEL[c]} | {_fmt(mean)} | {_fmt(p95)} | "
                  f"{worst:.1f} | {mean / vqf:.3f} |")
        orc = float(np.mean([oracle[r.name] for r in rows]))
        print(f"| {split} | {len(rows)} | rest oracle (diagnostic) | {_fmt(orc)} | | | "
              f"{orc / vqf:.3f} |")

    print("\n## XSENS MTi-30's own orientation (its mounting fitted to its own output)\n")
    print("| split | recordings | mean RMSE | mean p95 | max |")
    print("| --- | ---: | ---: | ---: | ---: |")
    xs: dict[str, list[rs.Score]] = {"tuning": [], "held out": []}
    for speed in rd.LEIRIA_SPEEDS:
        for path in (1, 2, 3, 4):
            if args.quick and speed not in rd.HELD_OUT_SPEEDS:
                continue
            score = rs.score_xsens(speed, path)
            if score is not None:
                xs["held out" if speed in rd.HELD_OUT_SPEEDS else "tuning"].append(score)
    for split, scores in xs.items():
        if scores:
            print(f"| {split} | {len(scores)} | "
                  f"{_fmt(float(np.mean([s.rmse_deg for s in scores])))} | "
                  f"{_fmt(float(np.mean([s.p95_deg for s in scores])))} | "
                  f"{max(s.max_deg for s in scores):.1f} |")

    print("\n## PX4 flight log: agreement with PX4's EKF2 (a reference, not truth), degrees\n")
    px4 = rs.score_px4(FILTERS, with_timed=True)
    print("| filter | RMSE | p95 | max | ratio to VQF |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for c in COLUMNS:
        s = px4[c]
        print(f"| {LABEL[c]} | {s.rmse_deg:.3f} | {s.p95_deg:.3f} | {s.max_deg:.3f} | "
              f"{s.rmse_deg / px4['vqf'].rmse_deg:.2f} |")
    held = splits["held out"]
    if held:
        ratio = rs.mean_rmse_deg(held, "ours") / rs.mean_rmse_deg(held, "vqf")
        verdict = "met" if ratio <= 0.9 else "not met"
        print(f"\nheld out: ours / VQF = {ratio:.3f} (target <= 0.9: {verdict}); "
              f"{time.monotonic() - t0:.0f} s in all")
    return 0 if all(math.isfinite(r.scores["ours"].rmse_deg) for r in results) else 1


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.result import run_captured

    sys.exit(run_captured("real_imu", ["companion/estimation", "companion/evaluation"], lambda: main(sys.argv[1:])))
