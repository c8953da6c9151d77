"""Decode cost of the device protocols, per frame (IMU, servo) and per epoch (GPS), in microseconds.

Run: ``.venv/bin/python bench/drivers_bench.py [--seconds 0.5]``. Streams come from the device
simulators; each row feeds the same stream three ways: one frame/epoch per ``feed`` call (what a
driver reading on a serial timeout sees), 1 s of data per call, and one byte per call (worst case).
The budget column is the device period, to put the cost in proportion.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from companion.drivers.gps_protocol import NmeaDecoder
from companion.drivers.imu_protocol import ImuDecoder
from companion.drivers.servo_protocol import PilotDecoder, PilotFrame, encode_pilot
from companion.sim.gps_sim import GpsSim, GpsSimConfig
from companion.sim.imu_sim import ImuSim


def imu_units(count: int) -> list[bytes]:
    sim = ImuSim(np.random.default_rng(1))
    return [sim.frame((0.1, -0.2, 0.05), (0.3, 0.1, -9.8)) for _ in range(count)]


def servo_units(count: int) -> list[bytes]:
    channels = (1500, 1510, 1200, 1490, 1900, 1500, 1500, 1500)
    return [encode_pilot(PilotFrame(n & 0xFF, True, False, channels, 98, 87)) for n in range(count)]


def gps_units(count: int, ashtech: bool) -> list[bytes]:
    sim = GpsSim(np.random.default_rng(2), GpsSimConfig(ashtech_pos=ashtech))
    return [sim.epoch(3600 + k / 10, 45.0, 9.0, 300.0, 20.0, 5.0, -1.0) for k in range(count)]


def time_feeds(
    make: Callable[[], object], chunks: Sequence[bytes], units: int, min_s: float
) -> float:
    """Mean microseconds per unit (frame/epoch), repeating the whole stream for >= min_s."""
    elapsed_ns = 0
    done = 0
    while elapsed_ns < min_s * 1e9:
        decoder = make()
        feed = decoder.feed  # type: ignore[attr-defined]
        start = time.perf_counter_ns()
        for i, chunk in enumerate(chunks):
            feed(chunk, i)
        elapsed_ns += time.perf_counter_ns() - start
        done += units
    return elapsed_ns / done / 1000.0


def rows(min_s: float) -> list[tuple[str, float, float, float, float]]:
    imu = imu_units(100)
    servo = servo_units(50)
    gps = gps_units(10, False)
    gps_pos = gps_units(10, True)
    expected = GpsSimConfig().expected_sentences
    expected_pos = GpsSimConfig(ashtech_pos=True).expected_sentences
    cases: list[tuple[str, Callable[[], object], list[bytes], float]] = [
        ("IMU fast frame (20 B)", ImuDecoder, imu, 10.0),
        ("servo pilot frame (23 B)", PilotDecoder, servo, 20.0),
        ("GPS epoch, 5 sentences", lambda: NmeaDecoder(expected_sentences=expected), gps, 100.0),
        (
            "GPS epoch, 5 + PASHR,POS",
            lambda: NmeaDecoder(expected_sentences=expected_pos),
            gps_pos,
            100.0,
        ),
    ]
    out = []
    for name, make, units, budget_ms in cases:
        joined = b"".join(units)
        per_unit = time_feeds(make, units, len(units), min_s)
        per_second = time_feeds(make, [joined], len(units), min_s)
        per_byte = time_feeds(
            make, [joined[i : i + 1] for i in range(len(joined))], len(units), min_s
        )
        out.append((name, per_unit, per_second, per_byte, budget_ms * 1000.0))
    return out


def sim_frame_us(profile: str, min_s: float) -> float:
    """Mean microseconds of one `ImuSim.frame` (10 ms of the simulated part) with a profile's
    every error term on, at a propeller's RPM (vibration) and the part's own warm-up."""
    from companion.sim.profiles import imu_profile

    sim = ImuSim(np.random.default_rng(1), imu_profile(profile).config)
    frame = sim.frame
    done, start = 0, time.perf_counter_ns()
    while time.perf_counter_ns() - start < min_s * 1e9:
        for _ in range(1000):
            frame((0.1, -0.2, 0.05), (0.3, 0.1, -9.8), 2400.0)
        done += 1000
    return (time.perf_counter_ns() - start) / done / 1000.0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=0.5, help="minimum timing per cell")
    parser.add_argument("--quick", action="store_true", help="short timings (0.1 s per cell)")
    args = parser.parse_args(argv)
    if args.quick:
        args.seconds = 0.1
    header = f"{'decode cost, us per unit':<28}{'1/feed':>10}{'1 s/feed':>10}{'byte/feed':>11}{'period':>10}"
    print(header)
    print("-" * len(header))
    for name, per_unit, per_second, per_byte, period_us in rows(args.seconds):
        print(f"{name:<28}{per_unit:>10.1f}{per_second:>10.1f}{per_byte:>11.1f}{period_us:>10.0f}")
    # the simulated part that makes the IMU's frames in `companion sim`: its budget is 45 us
    # of the 10 ms period, so that the world's 100 Hz tick stays a small part of a core at 5x
    print()
    header = f"{'ImuSim.frame, us per frame':<28}{'us':>10}{'budget':>10}"
    print(header)
    print("-" * len(header))
    for profile in ("simple", "consumer", "tactical"):
        print(f"{profile + ' profile':<28}{sim_frame_us(profile, args.seconds * 2):>10.1f}"
              f"{45:>10}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.result import run_captured

    sys.exit(run_captured("drivers", ["companion/drivers", "companion/sim"], main))
