"""Horizon detection benchmark: the thesis's baseline and the best method side by side.

Per data set and disturbance: roll error median and p90 (deg), offset error median and p90 (% of
image height), gross failures (roll error over 10 deg, offset error over 10 %, or no answer on a
frame that has a horizon), false detections on frames without a horizon, tracking on a synthetic
video, and frames per second at 320x240 on one core. Prints markdown.

    python bench/horizon_bench.py [--quick] [--methods baseline,robust] [--dev DIR]

Data sets: ``dev`` (the 108 real frames of the Horizon-UAV dataset in tests/data/horizon-dev), ``synth``
(rendered 320x240 scenes, half of them with roads and buildings), ``synth-lens`` (the same with
strong barrel distortion, detectors given the camera model). Each disturbance is applied with a
seed derived from the frame, so runs are repeatable.
"""

from __future__ import annotations

import os
import sys

# one core: must be set before numpy/OpenCV start their thread pools
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse  # noqa: E402
import csv  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable, Iterable  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from horizon.camera import CameraModel  # noqa: E402
from horizon.detector import create_detector  # noqa: E402
from horizon.estimate import HorizonEstimate  # noqa: E402
from horizon.geometry import OrientedLine, wrap_deg  # noqa: E402
from horizon.synth import (  # noqa: E402
    DISTURBANCES,
    SceneSpec,
    add_glare,
    add_noise,
    add_sync_stripes,
    apply_disturbance,
    random_spec,
    render_scene,
    render_through_lens,
)
from horizon.tracking import HorizonTracker  # noqa: E402

DEFAULT_DEV = REPO / "tests" / "data" / "horizon-dev"
GROSS_ROLL_DEG = 10.0
GROSS_OFFSET_PCT = 10.0
LENS = {"hfov_deg": 100.0, "k1": -0.28, "k2": 0.06}


@dataclass
class Sample:
    name: str
    image: np.ndarray
    truth: OrientedLine | None
    group: str


@dataclass
class Errors:
    roll_deg: float
    offset_pct: float
    gross: bool
    found: bool


def load_dev(folder: Path, step: int) -> list[Sample]:
    gt = folder / "gt.csv"
    if not gt.is_file():
        raise SystemExit(f"{gt}: the development frames' ground truth is missing "
                         "(it is tracked in git: restore tests/data)")
    out = []
    with gt.open(newline="") as f:
        rows = list(csv.DictReader(f))
    for row in rows[::step]:
        img = cv2.imread(str(folder / row["image"]), cv2.IMREAD_COLOR)
        if img is None:
            raise SystemExit(f"{folder / row['image']}: unreadable image")
        h, w = img.shape[:2]
        truth = OrientedLine.from_points(
            (float(row["x1"]), float(row["y1"])), (float(row["x2"]), float(row["y2"])), w, h
        )
        out.append(Sample(row["image"], img, truth, row["clip"]))
    return out


def make_synth(n: int, seed: int, lens: CameraModel | None = None) -> list[Sample]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        spec = random_spec(rng, 320, 240, clutter=i % 2 == 0)
        if lens is None:
            img, truth = render_scene(spec, rng)
        else:
            img, truth = render_through_lens(spec, lens, rng)
        out.append(Sample(f"synth-{i}", img, truth, "clutter" if i % 2 == 0 else "plain"))
    return out


def make_negatives(n: int, seed: int) -> list[Sample]:
    """Frames without a horizon: all ground (nose down), all sky, and a lost signal."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        kind = i % 3
        if kind == 2:
            img = rng.normal(128, 50, (240, 320, 3)).clip(0, 255).astype(np.uint8)
        else:
            offset = -1.6 if kind == 0 else 1.6
            spec = SceneSpec(320, 240, float(rng.uniform(-30, 30)), offset, 0.6, 0.2,
                             roads=2 if kind == 0 else 0, buildings=3 if kind == 0 else 0)
            img, _ = render_scene(spec, rng)
        out.append(Sample(f"none-{i}", img, None, ("ground", "sky", "signal lost")[kind]))
    return out


def errors(est: HorizonEstimate, truth: OrientedLine) -> Errors:
    if not est.found or est.roll_deg is None:
        return Errors(math.inf, math.inf, True, False)
    roll_err = abs(wrap_deg(est.roll_deg - truth.roll_deg))
    if est.offset_frac is None or math.isnan(truth.offset_frac):
        off_err = math.inf
    else:
        off_err = abs(est.offset_frac - truth.offset_frac) * 100.0
    gross = roll_err > GROSS_ROLL_DEG or off_err > GROSS_OFFSET_PCT
    return Errors(roll_err, off_err, gross, True)


def summary(errs: list[Errors]) -> dict[str, float]:
    roll = np.array([e.roll_deg for e in errs])
    off = np.array([e.offset_pct for e in errs])
    return {
        "n": len(errs),
        "found": 100.0 * float(np.mean([e.found for e in errs])),
        "roll_med": float(np.median(roll)),
        "roll_p90": float(np.percentile(roll, 90)),
        "off_med": float(np.median(off)),
        "off_p90": float(np.percentile(off, 90)),
        "gross": 100.0 * float(np.mean([e.gross for e in errs])),
    }


def fmt(x: float) -> str:
    return "inf" if not math.isfinite(x) else f"{x:.2f}"


def disturbed(samples: list[Sample], name: str, salt: int) -> Iterable[tuple[Sample, np.ndarray]]:
    for i, s in enumerate(samples):
        rng = np.random.default_rng([salt, list(DISTURBANCES).index(name), i])
        yield s, apply_disturbance(name, s.image, rng, s.truth)


def accuracy_tables(
    datasets: dict[str, tuple[list[Sample], CameraModel | None]],
    methods: list[str],
    disturbances: list[str],
) -> tuple[list[str], dict[tuple[str, str, str], list[Errors]]]:
    lines = [
        "| data set | disturbance | method | frames | found % | roll med | roll p90 | offset med % "
        "| offset p90 % | gross % |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    per: dict[tuple[str, str, str], list[Errors]] = {}
    for ds_name, (samples, camera) in datasets.items():
        if not samples:
            continue
        for d in disturbances:
            frames = list(disturbed(samples, d, 7))
            for m in methods:
                det = create_detector(m, camera)
                errs = []
                for s, img in frames:
                    assert s.truth is not None
                    errs.append(errors(det.detect(img), s.truth))
                per[(ds_name, d, m)] = errs
                r = summary(errs)
                lines.append(
                    f"| {ds_name} | {d} | {m} | {r['n']} | {r['found']:.0f} | {fmt(r['roll_med'])} "
                    f"| {fmt(r['roll_p90'])} | {fmt(r['off_med'])} | {fmt(r['off_p90'])} "
                    f"| {r['gross']:.1f} |"
                )
    return lines, per


def clip_table(
    samples: list[Sample], per: dict[tuple[str, str, str], list[Errors]], methods: list[str],
    disturbances: list[str],
) -> list[str]:
    clips = sorted({s.group for s in samples})
    lines = [
        "| disturbance | method | " + " | ".join(clips) + " |",
        "|---|---|" + "---:|" * len(clips),
    ]
    for d in disturbances:
        for m in methods:
            errs = per.get(("dev", d, m))
            if errs is None:
                continue
            cells = []
            for c in clips:
                sel = [e.gross for s, e in zip(samples, errs, strict=True) if s.group == c]
                cells.append(f"{100.0 * np.mean(sel):.0f}")
            lines.append(f"| {d} | {m} | " + " | ".join(cells) + " |")
    return lines


def negatives_table(samples: list[Sample], methods: list[str]) -> list[str]:
    kinds = sorted({s.group for s in samples})
    lines = ["| method | " + " | ".join(kinds) + " |", "|---|" + "---:|" * len(kinds)]
    for m in methods:
        det = create_detector(m)
        cells = []
        for k in kinds:
            sel = [det.detect(s.image).found for s in samples if s.group == k]
            cells.append(f"{100.0 * np.mean(sel):.0f}")
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return lines


def _heavy(name: str, img: np.ndarray, rng: np.random.Generator, truth: OrientedLine) -> np.ndarray:
    """Disturbances at the strong end, where single frames start to fail."""
    if name == "heavy noise":
        return add_noise(img, rng, float(rng.uniform(0.8, 1.0)))
    if name == "many stripes":
        return add_sync_stripes(img, rng, 4, str(rng.choice(["white", "black"])), (0.05, 0.1))
    if name == "strong glare":
        return apply_disturbance("glare", add_glare(img, rng, 0.9), rng, truth)
    return apply_disturbance(name, img, rng, truth)


def video_sequence(n: int, seed: int) -> list[Sample]:
    """A smooth manoeuvre in which about a third of the frames come in bursts of strong
    disturbances (the thesis saw them last a few frames at a time)."""
    rng = np.random.default_rng(seed)
    out = []
    names = ["heavy noise", "many stripes", "strong glare", "exposure", "noise", "stripes"]
    burst = ""
    burst_left = 0
    base = random_spec(rng, 320, 240, clutter=True)
    for i in range(n):
        t = i / 25.0
        roll = 35.0 * math.sin(0.5 * t) + 8.0 * math.sin(1.7 * t)
        offset = 0.15 * math.sin(0.3 * t + 1.0)
        spec = SceneSpec(320, 240, roll, offset, base.clouds, base.haze, base.roads, base.buildings)
        img, truth = render_scene(spec, np.random.default_rng([seed, 0]))
        if burst_left == 0 and rng.random() < 0.06:
            burst, burst_left = names[int(rng.integers(len(names)))], int(rng.integers(3, 10))
        if burst_left > 0:
            img = _heavy(burst, img, rng, truth)
            burst_left -= 1
        else:
            burst = ""
        out.append(Sample(f"video-{i}", img, truth, burst or "clean"))
    return out


def tracking_table(frames: list[Sample], methods: list[str]) -> list[str]:
    lines = [
        "| method | frames | roll med | roll p90 | offset med % | gross % |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    runs: list[tuple[str, Callable[[np.ndarray], HorizonEstimate]]] = []
    for m in methods:
        runs.append((m, create_detector(m).detect))
    if "robust" in methods:
        tracker = HorizonTracker()
        runs.append(("robust + tracking", tracker.update))
    for label, fn in runs:
        errs = []
        for s in frames:
            assert s.truth is not None
            errs.append(errors(fn(s.image), s.truth))
        r = summary(errs)
        lines.append(
            f"| {label} | {r['n']} | {fmt(r['roll_med'])} | {fmt(r['roll_p90'])} "
            f"| {fmt(r['off_med'])} | {r['gross']:.1f} |"
        )
    return lines


def fps_table(frames: list[np.ndarray], methods: list[str], min_cpu_s: float) -> list[str]:
    cv2.setNumThreads(1)
    lines = [
        "| method | frames | CPU ms/frame | FPS (one core, CPU time) | FPS (wall clock) |",
        "|---|---:|---:|---:|---:|",
    ]
    for m in methods:
        det = create_detector(m)
        for f in frames[:5]:
            det.detect(f)
        n = 0
        c0, w0 = time.process_time(), time.perf_counter()
        while time.process_time() - c0 < min_cpu_s or n < len(frames):
            det.detect(frames[n % len(frames)])
            n += 1
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        lines.append(
            f"| {m} | {n} | {1000 * cpu / n:.2f} | {n / cpu:.0f} | {n / wall:.0f} |"
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer frames, for a fast look")
    ap.add_argument("--methods", default="baseline,robust", help="comma-separated method names")
    ap.add_argument("--dev", type=Path, default=DEFAULT_DEV, help="real frames with gt.csv")
    ap.add_argument("--disturbances", default=",".join(DISTURBANCES))
    ap.add_argument("--seed", type=int, default=2003)
    args = ap.parse_args(argv)
    methods = [m for m in args.methods.split(",") if m]
    disturbances = [d for d in args.disturbances.split(",") if d]
    for d in disturbances:
        if d not in DISTURBANCES:
            ap.error(f"unknown disturbance {d!r}; choose from {', '.join(DISTURBANCES)}")
    cv2.setNumThreads(1)

    n_synth = 60 if args.quick else 300
    dev = load_dev(args.dev, 2 if args.quick else 1)
    lens = CameraModel.from_hfov(320, 240, LENS["hfov_deg"], LENS["k1"], LENS["k2"])
    datasets: dict[str, tuple[list[Sample], CameraModel | None]] = {
        "dev": (dev, None),
        "synth": (make_synth(n_synth, args.seed), None),
        "synth-lens": (make_synth(n_synth // 3, args.seed + 1, lens), lens),
    }
    t0 = time.perf_counter()
    print("## Horizon detection benchmark\n")
    print(f"Gross failure: roll error > {GROSS_ROLL_DEG:g} deg, offset error > "
          f"{GROSS_OFFSET_PCT:g} % of height, or no answer. Errors in deg and % of height.\n")
    lines, per = accuracy_tables(datasets, methods, disturbances)
    print("\n".join(lines))
    print("\n### Gross failures per clip (dev, %)\n")
    print("\n".join(clip_table(dev, per, methods, ["clean", "stripes", "noise"])))
    print("\n### False detections on frames without a horizon (%)\n")
    print("\n".join(negatives_table(make_negatives(30 if args.quick else 90, args.seed + 2), methods)))
    print("\n### Synthetic video with disturbance bursts\n")
    print("\n".join(tracking_table(video_sequence(150 if args.quick else 500, args.seed + 3), methods)))
    print("\n### Speed at 320x240, one core (cv2.setNumThreads(1), single-threaded BLAS)\n")
    fps_frames = [s.image for s in datasets["synth"][0][:40]]
    fps_frames += [cv2.resize(s.image, (320, 240), interpolation=cv2.INTER_AREA) for s in dev[:40]]
    print("\n".join(fps_table(fps_frames, methods, 1.0 if args.quick else 3.0)))
    print(f"\n(benchmark ran in {time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.result import run_captured

    sys.exit(run_captured("horizon", ["horizon"], main))
