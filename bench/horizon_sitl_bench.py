"""Horizon aiding in SITL: what the simulated camera and the real detector cost and deliver.

For each scenario's attitudes (``record_flight(FlightSpec(duration_s=60))``, its
``euler_true_rad``) frames are rendered at the true attitude by ``companion.sim.camera.SimCamera``
at its rate (10 Hz) and detected by the robust detector with tracking, as ``companion horizon
stream`` runs it. Per disturbance level: failures (no measurement), misses (no measurement
with the horizon in view), gross errors (sent, but roll off by > 10 deg or pitch by > 5 deg),
roll and pitch error against the truth, and the cost per frame (render + disturb + detect; wall
clock and the thread's CPU time, one OpenCV thread). A second table gives the cost at other
frame sizes. Prints markdown.

    python bench/horizon_sitl_bench.py [--quick] [--out bench/results/FILE.md]
"""

from __future__ import annotations

import os

# one core: must be set before numpy/OpenCV start their thread pools
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse  # noqa: E402
import io  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from contextlib import redirect_stdout  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from companion.evaluation.sitl import FlightSpec, record_flight  # noqa: E402
from companion.sim.camera import (  # noqa: E402
    DISTURBANCE_LEVELS,
    SimCamera,
    default_camera_model,
    horizon_measurements,
)
from horizon.camera import CameraModel  # noqa: E402


def _f(x: float | None, digits: int = 2) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def quality_table(scenarios: list[str], duration_s: float, seed: int) -> None:
    print(f"## Detector on simulated flights ({duration_s:.0f} s per scenario, seed {seed}, "
          f"{default_camera_model().width}x{default_camera_model().height}, 70 deg hfov, "
          "10 Hz, robust + tracking)\n")
    print("| scenario | disturbance | frames | horizon in view % | failures % | missed % | "
          "gross % | roll med | roll p95 | pitch med | pitch p95 | ms/frame med (wall) | "
          "p95 (wall) | ms/frame med (CPU) | p95 (CPU) |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for scenario in scenarios:
        rec = record_flight(FlightSpec(duration_s=duration_s, scenario=scenario, seed=seed))
        roll = np.degrees(rec.euler_true_rad[:, 0])
        pitch = np.degrees(rec.euler_true_rad[:, 1])
        for level in DISTURBANCE_LEVELS:
            cam = SimCamera(seed, disturbance=level)
            horizon_measurements(cam, rec.t_s, rec.euler_true_rad)
            s = cam.stats.summary()
            print(f"| {scenario} | {level} | {s['frames']} | {s['in_view_pct']:.1f} | "
                  f"{s['failure_pct']:.1f} | {s['missed_pct']:.1f} | "
                  f"{s['gross_pct']:.1f} | {_f(s['roll_err_med_deg'], 3)} | "
                  f"{_f(s['roll_err_p95_deg'], 3)} | {_f(s['pitch_err_med_deg'], 3)} | "
                  f"{_f(s['pitch_err_p95_deg'], 3)} | {_f(s['cost_med_ms'])} | "
                  f"{_f(s['cost_p95_ms'])} | {_f(s['cpu_med_ms'])} | {_f(s['cpu_p95_ms'])} |")
        print(f"\n(attitudes of `{scenario}`: roll {roll.min():.0f}..{roll.max():.0f} deg, "
              f"pitch {pitch.min():.0f}..{pitch.max():.0f} deg)\n")


def size_table(frames: int, seed: int) -> None:
    print(f"## Cost per frame by frame size ({frames} frames, random roll +-45 deg, "
          "pitch +-15 deg, 70 deg hfov)\n")
    print("| size | disturbance | panorama (once per scene) ms | render ms med | "
          "render + detect ms med (wall) | p95 (wall) | med (CPU) | p95 (CPU) |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    rng = np.random.default_rng(seed)
    att = np.radians(np.column_stack([rng.uniform(-45, 45, frames), rng.uniform(-15, 15, frames)]))
    for w, h in ((128, 96), (160, 120), (320, 240)):
        for level in ("none", "thesis"):
            cam = SimCamera(seed, CameraModel.from_hfov(w, h, 70.0), disturbance=level)
            t0 = time.perf_counter()
            cam.render(0.0, 0.0, 0.0, np.random.default_rng(0))  # builds the panorama
            pano_ms = (time.perf_counter() - t0) * 1e3
            render_ms = []
            for i in range(min(frames, 100)):
                t1 = time.perf_counter()
                cam.render(0.0, float(att[i, 0]), float(att[i, 1]), np.random.default_rng(i))
                render_ms.append((time.perf_counter() - t1) * 1e3)
            for i in range(frames):
                cam.capture(0.1 * i, float(att[i, 0]), float(att[i, 1]), i)
            s = cam.stats.summary()
            print(f"| {w}x{h} | {level} | {pano_ms:.0f} | {np.median(render_ms):.2f} | "
                  f"{_f(s['cost_med_ms'])} | {_f(s['cost_p95_ms'])} | {_f(s['cpu_med_ms'])} | "
                  f"{_f(s['cpu_p95_ms'])} |")
    print()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="20 s flights, 60 frames per size")
    ap.add_argument("--scenarios", default="auto,turns,aerobatic",
                    help="auto: the GPS-outage benchmark's sustained turn; aerobatic: loops and rolls")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, help="also write the output to this file")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    duration = 20.0 if args.quick else 60.0
    buf = io.StringIO()
    t0 = time.perf_counter()
    with redirect_stdout(buf):
        print("# `python bench/horizon_sitl_bench.py" + (" --quick" if args.quick else "") + "`\n")
        load = os.getloadavg()
        print(f"({platform.machine()}, {os.cpu_count()} CPUs, load average {load[0]:.2f} "
              f"(1 min) before the run; OpenCV {cv2.__version__}, one thread)\n")
        quality_table([s for s in args.scenarios.split(",") if s], duration, args.seed)
        size_table(60 if args.quick else 300, args.seed)
        print(f"(total {time.perf_counter() - t0:.0f} s)")
    text = buf.getvalue()
    print(text, end="")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
