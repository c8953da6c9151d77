"""Run the benchmarks that docs/benchmarks.md cites, with the settings it cites.

    python bench/run_all.py              # `make bench`: every figure in docs/benchmarks.md
    python bench/run_all.py --quick      # `make bench-quick`: a short smoke run of each
    python bench/run_all.py logs mavlink # only these (names without `_bench.py`)

Each benchmark prints its own markdown tables, with figures as ratios against the baseline it
measures in the same run. Before and after each one this script prints the machine's load
average, because latency, jitter and CPU figures depend on what else the machine was doing and
docs/benchmarks.md names the load next to every section.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

# (benchmark, arguments of the full run): the commands docs/benchmarks.md cites.
BENCHMARKS: list[tuple[str, list[str]]] = [
    ("watchdog", []),
    ("sitl", []),
    ("drivers", []),
    ("sim", []),
    ("logs", []),
    ("reader", []),
    ("mavlink", []),
    ("gcs_transfer", []),
    ("estimation", ["--full"]),
    ("estimation_sitl", ["--second-flight"]),
    ("estimation_budget", []),
    ("horizon", []),
    ("report", []),
    ("dataset", []),
    ("fleet_router", []),
    ("wakeup", []),
    ("lockstep", []),
    ("real_imu", []),
    ("replay", []),
    ("replay_logs", []),
]


def _load() -> str:
    one, five, _ = os.getloadavg()
    return f"load average {one:.2f} (1 min), {five:.2f} (5 min) on {os.cpu_count()} CPUs"


def main(argv: list[str]) -> int:
    quick = "--quick" in argv
    chosen = [a for a in argv if not a.startswith("-")]
    known = {name for name, _ in BENCHMARKS}
    unknown = sorted(set(chosen) - known)
    if unknown:
        print(f"run_all: unknown benchmark(s) {unknown}; choose from {sorted(known)}",
              file=sys.stderr)
        return 2
    failures = 0
    started = time.monotonic()
    for name, full_args in BENCHMARKS:
        if chosen and name not in chosen:
            continue
        args = ["--quick"] if quick else full_args
        script = HERE / f"{name}_bench.py"
        command = " ".join(["python", f"bench/{script.name}", *args])
        print(f"\n# `{command}`\n\n(before: {_load()})\n", flush=True)
        t0 = time.monotonic()
        code = subprocess.call([sys.executable, str(script), *args])
        print(f"\n({script.name}: exit {code}, {time.monotonic() - t0:.0f} s; after: {_load()})",
              flush=True)
        failures += code != 0
    # the total is what README quotes for `make bench`
    print(f"\n(run_all: {failures} failed, {time.monotonic() - started:.0f} s in all)", flush=True)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
