"""Replay log reading: our DataFlash reader against pymavlink's DFReader on a 20-minute log.

    python bench/replay_bench.py [--minutes M] [--json PATH] [--md PATH]

No public 20-minute DataFlash log with a licence that lets it be kept was found small enough, so
the input is made from the real one in tests/data/replay/arduplane-pymavlink-test.bin
(ArduPlane 3.8 on a Pixhawk, 1 s, IMU and IMU2 at 50 Hz, GPS, ATT, AHR2, NKF1 and 47 other
types): its records are repeated with TimeUS shifted by the copy's length
(`tests/support/replay_logs.py::repeat_dataflash`) until the log lasts M minutes (default 20).

Throughput: IMU samples a second (IMU and IMU2 together) of `read_flight_log` (everything the
replay takes: IMU, GPS, ATT/AHR2/NKF1, decoded to arrays) and of pymavlink's `DFReader_binary`
asked with `recv_match` for the same seven types, each in its own subprocess, best of N, in one
run; the ratio is ours / pymavlink's. Memory: each reader's peak resident set (ru_maxrss of its
subprocess, after importing numpy and pymavlink) on the same log, and the Python heap peak of
ours (tracemalloc, a separate run).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SOURCE = ROOT / "tests" / "data" / "replay" / "arduplane-pymavlink-test.bin"
TYPES = ["IMU", "IMU2", "GPS", "ATT", "AHR2", "NKF1", "FMT"]


def child(which: str, path: str, trace: bool) -> dict[str, float]:
    """One reading in this process: seconds, IMU samples, peak RSS (and heap peak)."""
    import tracemalloc

    import numpy  # noqa: F401 - imported before the baseline, as both readers need it
    from pymavlink import DFReader

    from companion.estimation.replay.sources import close_dfreader, read_flight_log

    base_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    if trace:
        tracemalloc.start()
    t0 = time.perf_counter()
    if which == "ours":
        fl = read_flight_log(path)
        imu = len(fl.imu.t_us) * len(fl.info["imu_instances"])
    else:
        reader = DFReader.DFReader_binary(path, zero_time_base=False)
        imu = 0
        while (m := reader.recv_match(type=TYPES[:-1])) is not None:
            imu += m.get_type() in ("IMU", "IMU2")
        close_dfreader(reader)
    wall = time.perf_counter() - t0
    out = {"wall_s": wall, "imu_samples": imu,
           "maxrss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
           "baseline_rss_mib": base_kib / 1024}
    if trace:
        out["heap_peak_mib"] = tracemalloc.get_traced_memory()[1] / 2**20
    return out


def run_child(which: str, path: Path, trace: bool = False) -> dict[str, float]:
    proc = subprocess.run([sys.executable, __file__, "--child", which, str(path)]
                          + (["--trace"] if trace else []), capture_output=True, text=True,
                          check=True, timeout=1800, cwd=ROOT,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=20.0)
    ap.add_argument("--repeat", type=int, default=3, help="runs of each reader (best kept)")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--md", type=Path)
    ap.add_argument("--child", nargs=2, metavar=("WHICH", "PATH"), help=argparse.SUPPRESS)
    ap.add_argument("--trace", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.child[0], args.child[1], args.trace)))
        return 0
    from tests.support.replay_logs import repeat_dataflash

    data = SOURCE.read_bytes()
    copy_us = 1_000_000  # the source's timeline spans just over 1 s: copies 1 s apart
    copies = int(round(args.minutes * 60))
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "long.bin"
        path.write_bytes(repeat_dataflash(data, copies, copy_us))
        size = path.stat().st_size
        runs: dict[str, list[dict[str, float]]] = {"ours": [], "pymavlink": []}
        for _ in range(args.repeat):
            for which in runs:
                runs[which].append(run_child(which, path))
        traced = run_child("ours", path, trace=True)
    best = {w: min(r, key=lambda x: x["wall_s"]) for w, r in runs.items()}
    rate = {w: b["imu_samples"] / b["wall_s"] for w, b in best.items()}
    commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                            cwd=ROOT).stdout.strip()
    result = {
        "command": "python bench/replay_bench.py " + " ".join(sys.argv[1:]),
        "commit": commit, "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "machine": {"nproc": os.cpu_count(), "python": platform.python_version(),
                    "platform": platform.platform(), "load_before": load_before,
                    "load_after": os.getloadavg()},
        "log": {"source": str(SOURCE.relative_to(ROOT)), "copies": copies,
                "minutes": copies * copy_us / 60e6, "size_mib": size / 2**20},
        "runs": runs, "best": best,
        "imu_samples_per_s": rate, "ratio_ours_over_pymavlink": rate["ours"] / rate["pymavlink"],
        "ours_heap_peak_mib": traced["heap_peak_mib"],
    }
    md = [
        f"# Replay log reading, {result['date'][:10]} (commit {commit[:8]})", "",
        f"Command: `{result['command']}`. Log: {copies} copies of "
        f"`{result['log']['source']}` (ArduPlane 3.8, IMU+IMU2 at 50 Hz), TimeUS shifted: "
        f"{result['log']['minutes']:.0f} minutes, {size / 2**20:.1f} MiB. Best of "
        f"{args.repeat}, each reader in its own process; {os.cpu_count()} cores shared, load "
        f"{load_before[0]:.2f} before.", "",
        "| reader | IMU samples | wall s | IMU samples/s | peak RSS MiB (baseline) |",
        "|---|---:|---:|---:|---:|",
    ]
    for w, b in best.items():
        md.append(f"| {w} | {b['imu_samples']:.0f} | {b['wall_s']:.2f} | {rate[w]:,.0f} | "
                  f"{b['maxrss_mib']:.0f} ({b['baseline_rss_mib']:.0f}) |")
    md += ["", f"Ratio ours / pymavlink: {result['ratio_ours_over_pymavlink']:.1f}x. Python heap "
           f"peak of ours (tracemalloc): {traced['heap_peak_mib']:.1f} MiB for a "
           f"{size / 2**20:.1f} MiB log."]
    text = "\n".join(md) + "\n"
    print(text)
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")
    if args.md:
        args.md.write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.result import run_captured

    raise SystemExit(run_captured("replay", ["companion/estimation/replay", "companion/logs"],
                                  main))
