"""The estimator's parameters: their declaration and their defaults by suffix.

Separate from the thread so that what reads the defaults (the replay, the calibration command,
the evaluations) does not load the thread, its watchdog and its task table, and so the
defaults are derived in one place from the one declaration.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

from companion.core.params import ParamSpec, float_param, int_param

__all__ = ["estimator_param_defaults", "estimator_param_specs"]


def estimator_param_specs(p: str) -> list[ParamSpec]:
    """The estimator thread's parameters under the prefix ``p`` (``EST`` on the vehicle)."""
    return [
        float_param(f"{p}_INIT_S", 1.0, 0.1, 60.0, "s",
                    "Initial phase: IMU averaging time that levels the attitude and takes "
                    "the gyro bias before the filter starts."),
        float_param(f"{p}_GYR_NSD", 0.001, 1e-5, 1.0, "rad/s/rtHz",
                    "Gyro white-noise density (angle random walk), widened beyond a "
                    "datasheet's to cover vibration and g-sensitivity the filter does not "
                    "model."),
        float_param(f"{p}_ACC_NSD", 0.05, 1e-4, 5.0, "m/s^2/rtHz",
                    "Accelerometer white-noise density."),
        float_param(f"{p}_GB_RW", 2e-4, 1e-8, 0.01, "rad/s/rts",
                    "Gyro bias random walk (wide enough to follow a consumer part warming "
                    "up: about 1 deg/s over its first minutes)."),
        float_param(f"{p}_AB_RW", 1e-3, 1e-7, 0.1, "m/s^2/rts",
                    "Accelerometer bias random walk."),
        float_param(f"{p}_GS_STD", 0.015, 0.0, 0.1, "",
                    "1-sigma of each element of the gyro's scale-factor and cross-axis "
                    "error before the flight (fraction; a consumer part's +-3 % "
                    "tolerance is about 0.01 at 1 sigma, and the prior is kept wider "
                    "than that): the filter estimates the 3x3 error in turns. 0 takes "
                    "the gyro's scale as exact."),
        float_param(f"{p}_GB_TEMP", 1.5e-3, 0.0, 0.01, "rad/s/degC",
                    "Gyro bias change per degree of IMU temperature, 1-sigma: the prior "
                    "of the coefficient the filter estimates per axis while the part "
                    "warms up (a consumer MEMS part's datasheet allows about 0.05 deg/s/C "
                    "at 1 sigma; the prior is kept wider, 0.086 deg/s/C). 0 ignores the "
                    "temperature."),
        *[float_param(f"{p}_GM_{r}{c}", 0.0, -0.1, 0.1, "",
                      f"Gyro matrix error, row {r.lower()}, column {c.lower()} (the part "
                      "reads (I + M) w + bias): where the filter's estimate starts, from "
                      "what a previous flight of this part learnt (`companion estimation "
                      "calibration`); EST_GS_STD is its 1-sigma. 0 with no such flight.")
          for r in "XYZ" for c in "XYZ"],
        *[float_param(f"{p}_GT_{a}", 0.0, -0.01, 0.01, "rad/s/degC",
                      f"Gyro {a.lower()} bias temperature coefficient where the filter's "
                      "estimate starts, from a previous flight of this part (`companion "
                      "estimation calibration`); EST_GB_TEMP is its 1-sigma.")
          for a in "XYZ"],
        float_param(f"{p}_AB_TEMP", 1.5e-3, 0.0, 0.1, "m/s^2/degC",
                    "Accelerometer bias change per degree of IMU temperature, 1-sigma "
                    "(0.15 mg/C). 0 ignores the temperature."),
        float_param(f"{p}_GPS_HSTD", 1.0, 0.05, 100.0, "m",
                    "GPS horizontal position 1-sigma per unit HDOP."),
        float_param(f"{p}_GPS_VSTD", 2.0, 0.05, 100.0, "m",
                    "GPS vertical position 1-sigma (GST altitude std used when larger)."),
        float_param(f"{p}_TRIM_ROLL", 0.0, -0.5, 0.5, "rad",
                    "IMU board roll against the airframe (level calibration): samples are "
                    "turned into airframe axes before the filter."),
        float_param(f"{p}_TRIM_PITCH", 0.0, -0.5, 0.5, "rad",
                    "IMU board pitch against the airframe (level calibration)."),
        float_param(f"{p}_TRIM_YAW", 0.0, -0.5, 0.5, "rad",
                    "IMU board yaw against the airframe (a level calibration cannot see it; "
                    "measure it on the ground)."),
        int_param(f"{p}_TRIM_BIAS", 1, 0, 1, "",
                  "1: TRIM_ROLL/PITCH come from a level calibration, which read that "
                  "moment's accelerometer bias as a board tilt; the filter gives that tilt "
                  "back as it learns the bias in flight. 0 for trims measured otherwise "
                  "(no effect while both are 0)."),
        float_param(f"{p}_GPS_VEL", 0.25, 0.01, 10.0, "m/s",
                    "GPS velocity 1-sigma (a receiver's own figure is about 0.05 m/s; "
                    "the rest covers its latency jitter in turns)."),
        float_param(f"{p}_GPS_LAG", 0.05, 0.0, 0.5, "s",
                    "Receiver output delay beyond the latency the driver measures: the "
                    "starting guess, refined online unless GPS_LAGSD is 0."),
        float_param(f"{p}_GPS_LAGSD", 0.1, 0.0, 0.5, "s",
                    "1-sigma of the GPS_LAG guess; the filter estimates the delay from "
                    "turns and accelerations. 0 trusts GPS_LAG as exact."),
        int_param(f"{p}_HZN_USE", 1, 0, 1, "",
                  "1 fuses horizon attitude (HORIZON_ATTITUDE / MAVLink) weighted by quality."),
        float_param(f"{p}_HZN_STD", 0.05, 0.001, 1.0, "rad",
                    "Horizon roll/pitch 1-sigma at quality 1."),
        int_param(f"{p}_HDG_USE", 1, 0, 1, "",
                  "1 fuses a dual-antenna receiver's heading (NMEA HDT, GPS_HDT) with its "
                  "fix. Only an unbiased heading helps: in a turn a heading error becomes "
                  "a tilt error, so measure HDG_OFS on the ground."),
        float_param(f"{p}_HDG_STD", 0.01, 0.0001, 1.0, "rad",
                    "1-sigma of the receiver's heading (about the relative position's "
                    "error over the antenna baseline: 0.01 rad for 5 mm over 0.5 m)."),
        float_param(f"{p}_HDG_OFS", 0.0, -math.pi, math.pi, "rad",
                    "Yaw of the antenna baseline (first to second antenna) against the "
                    "airframe's forward axis, clockwise: 0 with the second antenna straight "
                    "ahead of the first, pi/2 with the first on the left wing and the "
                    "second on the right."),
    ]


def estimator_param_defaults(prefix: str,
                             overrides: Mapping[str, float] | None = None) -> dict[str, float]:
    """The estimator's parameter defaults by suffix (``GPS_LAG``, ``GYR_NSD``...), with
    ``overrides`` applied (by suffix or by full name under ``prefix``).

    Read from the declaration, so evaluations and tools follow the thread's defaults instead of
    copying them; an unknown override is refused (ValueError).
    """
    params = {spec.name.removeprefix(prefix + "_"): float(spec.default)
              for spec in estimator_param_specs(prefix)}
    for name, value in (overrides or {}).items():
        key = name.upper().removeprefix(prefix + "_")
        if key not in params:
            raise ValueError(f"unknown estimator parameter {name!r} "
                             f"(known: {', '.join(sorted(params))})")
        params[key] = float(value)
    return params
