"""Campaign dataset benchmark: export 100 flights into one Parquet dataset, query it with DuckDB.

    python bench/dataset_bench.py [--flights N] [--repeat R]

The 100 flights are NOT 100 flights flown: one `companion sim --vehicles 2` run (8 s, 5x
faster than real time, a GPS thread fault at 3 s) gives 2 real flights, which are copied into N
flight directories with distinct names and vehicle ids (run.json's vehicle id rewritten; the
logs are byte-identical copies). Every figure is a ratio against a baseline measured in the
same run on the same files:

* export of all N flights (`export_flight`: read, convert, write Parquet) against reading the
  same bytes with `read_log` alone (the least any export must do);
* each query (`companion.logs.dataset.query`: connection, views and SQL) against pyarrow
  reading the same columns of the dataset with hive partitioning and pandas grouping them.

Times are the best of R repetitions (the export: one, it writes the dataset). The machine's load
average is printed with the table: other work running shows in the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from companion.logs.dataset import export_flight, query  # noqa: E402
from companion.logs.reader import read_log  # noqa: E402

SIM_TIMEOUT_S = 120
RESTARTS_SQL = "SELECT thread, sum(restarts) AS restarts FROM restarts GROUP BY thread"
MEAN_SQL = "SELECT vehicle, flight, avg(p_rad_s) AS mean_p FROM imu_fmt1 GROUP BY vehicle, flight"


def fly(work: Path) -> list[Path]:
    cmd = [sys.executable, "-m", "companion", "sim", "--duration", "8", "--fast", "--vehicles", "2",
           "--mavlink", "none", "--no-legacy", "--thread-fault", "gps:raise:3",
           "--log-dir", str(work / "flown"), "--params-file", str(work / "p.parm")]
    done = subprocess.run(cmd, cwd=work, capture_output=True, text=True, timeout=SIM_TIMEOUT_S)
    if done.returncode != 0:
        sys.exit(f"companion sim failed:\n{done.stderr[-2000:]}")
    return sorted((work / "flown").iterdir())


def copies(real: list[Path], n: int, dest: Path) -> list[Path]:
    """N flight directories copied from the real ones: distinct names, vehicle ids 1..10."""
    out = []
    for k in range(n):
        src = real[k % len(real)]
        d = dest / f"{src.name.split('-')[0]}-c{k:03d}"
        shutil.copytree(src, d)
        run = json.loads((d / "run.json").read_text())
        run["config"]["vehicle"]["id"] = k % 10 + 1
        run["parameters"]["SYS_VEHICLE_ID"] = k % 10 + 1
        (d / "run.json").write_text(json.dumps(run))
        out.append(d)
    return out


def best(fn: Callable[[], object], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flights", type=int, default=100)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="10 flights, one repeat (a smoke run)")
    args = ap.parse_args()
    if args.quick:
        args.flights, args.repeat = 10, 1
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="dataset-bench-") as tmp:
        work = Path(tmp)
        real = fly(work)
        flights = copies(real, args.flights, work / "campaign")
        bins = [p for f in flights for p in sorted(f.glob("*.bin"))]
        size_bin = sum(p.stat().st_size for p in bins)

        t_read = best(lambda: [read_log(p, salvage=True) for p in bins], args.repeat)
        ds = work / "ds"
        t0 = time.perf_counter()
        rows = sum(export_flight(f, ds).records for f in flights)
        t_export = time.perf_counter() - t0
        size_ds = sum(p.stat().st_size for p in ds.rglob("*.parquet"))

        import pyarrow.dataset as pads

        def arrow_restarts() -> object:
            t = pads.dataset(ds / "restarts", format="parquet").to_table(
                columns=["thread", "restarts"]).to_pandas()
            return t.groupby("thread")["restarts"].sum()

        def arrow_mean() -> object:
            files = [str(p) for p in (ds / "streams").glob("*/*/stream=imu_fmt1/*.parquet")]
            t = pads.dataset(files, format="parquet", partitioning="hive",
                             partition_base_dir=str(ds / "streams")).to_table(
                columns=["vehicle", "flight", "p_rad_s"]).to_pandas()
            return t.groupby(["vehicle", "flight"])["p_rad_s"].mean()

        _, r = query(ds, RESTARTS_SQL)
        assert dict(r)["gps"] == args.flights  # one GPS restart per flight, copied N times
        _, r = query(ds, MEAN_SQL)
        assert len(r) == args.flights
        t_q1 = best(lambda: query(ds, RESTARTS_SQL), args.repeat)
        t_q1_base = best(arrow_restarts, args.repeat)
        t_q2 = best(lambda: query(ds, MEAN_SQL), args.repeat)
        t_q2_base = best(arrow_mean, args.repeat)

    load_after = os.getloadavg()
    print(f"{args.flights} flight directories COPIED from {len(real)} real 8 s SITL flights "
          "(distinct names, vehicle ids 1..10, byte-identical logs); "
          f"{len(bins)} logs, {size_bin / 1e6:.1f} MB of .bin, {rows} rows, "
          f"dataset {size_ds / 1e6:.1f} MB of Parquet")
    print(f"load average before {load_before[0]:.2f} {load_before[1]:.2f} {load_before[2]:.2f}, "
          f"after {load_after[0]:.2f} {load_after[1]:.2f} {load_after[2]:.2f} "
          f"({os.cpu_count()} CPUs)\n")
    print("| measurement | time | baseline | baseline time | ratio |")
    print("|---|---:|---|---:|---:|")
    table = [
        (f"export {args.flights} flights (export_flight)", t_export,
         "read_log of the same .bin files", t_read),
        ("query: restarts per thread (DuckDB, views included)", t_q1,
         "pyarrow.dataset + pandas groupby", t_q1_base),
        ("query: mean p_rad_s per flight over imu_fmt1", t_q2,
         "pyarrow.dataset (same glob, hive) + pandas", t_q2_base),
    ]
    for what, t, base, tb in table:
        print(f"| {what} | {t * 1e3:.0f} ms | {base} | {tb * 1e3:.0f} ms | {t / tb:.2f} |")
    print(f"\nexport: {t_export / args.flights * 1e3:.1f} ms per flight, "
          f"{rows / t_export / 1e6:.2f} M rows/s")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.result import run_captured

    sys.exit(run_captured("dataset", ["companion/logs"], main))
