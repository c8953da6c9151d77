"""Run every benchmark in bench/ (`make bench`); pass --quick for a short smoke run.

Each benchmark prints its own markdown tables with figures as ratios against the baseline it
measures in the same run; docs/benchmarks.md records them with the command that produced them.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main() -> int:
    extra = sys.argv[1:]
    failures = 0
    for script in sorted(HERE.glob("*_bench.py")):
        print(f"\n# {script.name} {' '.join(extra)}\n", flush=True)
        t0 = time.monotonic()
        code = subprocess.call([sys.executable, str(script), *extra])
        print(f"\n({script.name}: exit {code}, {time.monotonic() - t0:.0f} s)", flush=True)
        failures += code != 0
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
