"""How much faster than real time the flight model and the scripted pilot run, per aircraft.

The whole SITL target is 5x real time with the runtime, device simulators and estimator on two
cores, so the flight side must leave most of a core free. Three figures per aircraft:

- ``step``: ``FlightModel.step`` alone at the 100 Hz model rate (JSBSim plus our bookkeeping);
- ``step+truth``: the same plus ``truth()`` every step, which SITL needs for the 100 Hz IMU;
- ``+pilot``: the same plus the pilot at 50 Hz and the channel mapping (``pilot.fly``).

Both wall-clock and process-CPU real-time factors are printed: on a shared machine the CPU
figure is the one that says what the code costs.

Usage: ``python bench/sim_bench.py [--duration 300] [--scenario mixed] [--aircraft c172p ...]``
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

from companion.sim.aircraft import AIRCRAFT
from companion.sim.flight import FlightModel
from companion.sim.pilot import Pilot, fly
from companion.sim.scenarios import SCENARIOS


def _timed(work: Callable[[], None]) -> tuple[float, float]:
    wall0, cpu0 = time.perf_counter(), time.process_time()
    work()
    return time.perf_counter() - wall0, time.process_time() - cpu0


def bench_aircraft(
    aircraft: str, duration_s: float, scenario: str
) -> list[tuple[str, float, float, float]]:
    """Rows of (what, model steps per CPU second, wall RTF, CPU RTF)."""
    rows = []

    model = FlightModel(aircraft)
    n = int(duration_s * model.rate_hz)

    def step_only() -> None:
        for _ in range(n):
            model.step(model.dt_s)

    wall, cpu = _timed(step_only)
    rows.append(("step", n / cpu, duration_s / wall, duration_s / cpu))

    model = FlightModel(aircraft)

    def step_truth() -> None:
        for _ in range(n):
            model.step(model.dt_s)
            model.truth()

    wall, cpu = _timed(step_truth)
    rows.append(("step+truth", n / cpu, duration_s / wall, duration_s / cpu))

    model = FlightModel(aircraft)
    pilot = Pilot(scenario, 1, aircraft=aircraft, trim_throttle=model.trim_controls.throttle)

    def with_pilot() -> None:
        for _ in fly(model, pilot, duration_s):
            pass

    wall, cpu = _timed(with_pilot)
    rows.append((f"+pilot ({scenario})", n / cpu, duration_s / wall, duration_s / cpu))
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=300.0, help="simulated seconds per run")
    parser.add_argument("--scenario", default="mixed", choices=SCENARIOS)
    parser.add_argument("--aircraft", nargs="*", default=sorted(AIRCRAFT), choices=sorted(AIRCRAFT))
    parser.add_argument("--quick", action="store_true", help="30 simulated seconds per run")
    args = parser.parse_args()
    if args.quick:
        args.duration = 30.0

    print(f"simulated {args.duration:.0f} s per run, model at 100 Hz, pilot at 50 Hz")
    print(f"{'aircraft':<8} {'run':<18} {'steps/s (cpu)':>14} {'RTF wall':>9} {'RTF cpu':>8}")
    for aircraft in args.aircraft:
        for what, steps_s, rtf_wall, rtf_cpu in bench_aircraft(
            aircraft, args.duration, args.scenario
        ):
            print(f"{aircraft:<8} {what:<18} {steps_s:>14,.0f} {rtf_wall:>8.0f}x {rtf_cpu:>7.0f}x")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.result import run_captured

    sys.exit(run_captured("sim", ["companion/sim"], main))
