"""`companion estimation calibration LOG`: the gyro calibration a flight learnt, as parameters
for the next flight (companion.estimation.calibration).

Registering the command imports nothing but argparse; the log reader loads when it runs.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

EXIT_BAD_LOG = 2
EXIT_OUTPUT = 1


def add_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calibration", help="turn the gyro calibration a flight learnt into parameters for "
                            "the next flight",
        description="Read the last calibration record of a flight's estimator.bin (the gyro's "
                    "scale-factor and cross-axis matrix and its bias's temperature coefficient, "
                    "with their 1-sigma) and write the parameters that start the next flight "
                    "of the same IMU from it: EST_GM_*, EST_GT_* and narrower EST_GS_STD and "
                    "EST_GB_TEMP. Load them with --params-file, or `param load` in MAVProxy.")
    p.add_argument("log", type=Path, help="a flight directory or its estimator.bin")
    p.add_argument("-o", "--output", type=Path, metavar="FILE",
                   help="write the parameter file here (default: print it)")
    p.add_argument("--json", action="store_true",
                   help="print what was learnt and the parameters as JSON instead")
    p.set_defaults(func=cmd_calibration)


def _param_text(source: Path, flight_s: float, params: dict[str, float]) -> str:
    from companion.core.params import ParamType, format_value

    lines = [f"# gyro calibration learnt by the estimator in {source} ({flight_s:.0f} s of "
             "flight)",
             "# companion estimation calibration: start the next flight of this IMU from it"]
    lines += [f"{name:<16} {format_value(ParamType.FLOAT32, value)}"
              for name, value in params.items()]
    return "\n".join(lines) + "\n"


def cmd_calibration(args: argparse.Namespace) -> int:
    from companion.estimation.calibration import (
        CalibrationLogError,
        learnt_from_log,
        next_flight_params,
    )
    from companion.estimation.params import estimator_param_defaults
    from companion.vehicle import VEHICLE

    try:
        cal = learnt_from_log(args.log)
    except CalibrationLogError as exc:
        print(f"companion estimation calibration: {exc}", file=sys.stderr)
        return EXIT_BAD_LOG
    params = next_flight_params(
        cal, estimator_param_defaults(VEHICLE["estimator"].task.param_prefix))
    if args.json:
        out: dict[str, Any] = {
            "log": str(args.log), "flight_s": round(cal.flight_s, 1),
            "gyro_matrix": [list(cal.matrix[r * 3:r * 3 + 3]) for r in range(3)],
            "gyro_matrix_std": [list(cal.matrix_std[r * 3:r * 3 + 3]) for r in range(3)],
            "gyro_temp_rad_s_per_c": list(cal.temp_rad_s_per_c),
            "gyro_temp_std_rad_s_per_c": list(cal.temp_std_rad_s_per_c),
            "params": params}
        print(json.dumps(out, indent=2))
    text = _param_text(args.log, cal.flight_s, params)
    if args.output is None:
        if not args.json:
            sys.stdout.write(text)
        return 0
    try:
        from companion.core.files import atomic_write_text
        atomic_write_text(args.output, text)
    except OSError as exc:
        print(f"companion estimation calibration: cannot write {args.output}: "
              f"{exc.strerror or exc}", file=sys.stderr)
        return EXIT_OUTPUT
    if not args.json:
        scale = [cal.matrix[0], cal.matrix[4], cal.matrix[8]]
        print(f"{args.output}: {len(params)} parameters from {cal.flight_s:.0f} s of flight "
              f"(scale factors {', '.join(f'{100 * s:+.2f} %' for s in scale)}; temperature "
              f"coefficients {', '.join(f'{math.degrees(k):+.4f}' for k in cal.temp_rad_s_per_c)}"
              " deg/s/C)")
    return 0
