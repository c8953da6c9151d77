"""`companion sim`'s command line to the simulated world: what each aircraft of a fleet flies."""

from __future__ import annotations

from companion.cli import build_parser
from companion.sim.cli import sim_options
from companion.sim.runner import SimOptions


def options(*argv: str) -> SimOptions:
    return sim_options(build_parser().parse_args(["sim", *argv]), 1.0)


def test_fleet_aircraft_carry_parts_of_their_own() -> None:
    # run_fleet starts aircraft i with --seed-offset i-1: the same --imu-seed must not give
    # K aircraft one IMU part
    first = options("--seed", "3", "--imu-seed", "40")
    third = options("--seed", "3", "--imu-seed", "40", "--seed-offset", "2")
    assert (first.seed, first.imu_seed) == (3, 40)
    assert (third.seed, third.imu_seed) == (5, 42)


def test_without_imu_seed_the_part_follows_the_seed() -> None:
    assert options("--seed", "3", "--seed-offset", "1").imu_seed is None
