"""The gyro calibration a flight learnt, handed to the next flight of the same part.

The estimator learns the gyro's scale-factor and cross-axis matrix ``M`` and its bias's
temperature coefficient in flight (companion.estimation.eskf). Both belong to the part and its
mounting, not to one power-on (the turn-on bias, which does change, is not carried over), so
what one flight learnt is the best prior for the next. That matters because a steady turn hides
a rotation about the specific force from the GPS: until the filter has flown turns both ways,
the gyro's error about the body z axis goes straight into the tilt, and a flight's largest
tilt errors fall in its first turns.

The estimator thread logs the estimate with its 1-sigma about once a second (``FMT_CAL``
records of ``estimator.bin``); :func:`learnt_from_log` reads the last one and
:func:`next_flight_params` turns it into ``EST_GM_*``, ``EST_GT_*`` and narrower priors
``EST_GS_STD`` / ``EST_GB_TEMP``, which ``companion estimation calibration`` writes as a
parameter file for ``--params-file`` (or MAVProxy's ``param load``). This is what ArduPilot and
PX4 do with the calibrations they learn (learnt compass offsets, thermal calibration saved
to parameters), applied to the two things a GPS/INS filter can learn of a gyro.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

GYRO_MATRIX_PARAMS = tuple(f"GM_{r}{c}" for r in "XYZ" for c in "XYZ")
"""The estimator's parameters (without the ``EST_`` prefix) that start ``M``, row-major."""
GYRO_TEMP_PARAMS = ("GT_X", "GT_Y", "GT_Z")
"""... and the temperature coefficient, rad/s per degree C."""
MIN_FLIGHT_S = 60.0
"""A log with less estimator time than this has not seen enough turns to learn from."""
PRIOR_SCALE = 0.6
"""The next flight's prior 1-sigma is this times the 1-sigma the filter reports for what it
learnt. The filter's own figure is pessimistic: its gyro noise is widened to cover vibration
and g-sensitivity, so on the tuning flights (seeds 5-12, 120 s, 32 flights) the matrix's
actual error was 0.0049 RMS against 0.0078 reported (0.59 of it); the next prior is the error
the estimate actually has. 0.4-1.0 scored alike there on the following flights."""
MIN_GS_STD = 0.004
"""Floor of the next flight's ``EST_GS_STD`` (a consumer part's scale factor moves about
this much between a cold and a warm flight)."""
MIN_GB_TEMP_RAD_S_PER_C = 2e-4
"""Floor of the next flight's ``EST_GB_TEMP``: a fit over one warm-up's few degrees does not
pin the coefficient down further."""


class CalibrationLogError(ValueError):
    """The log holds no usable calibration; the message names the file and why."""


@dataclass(frozen=True)
class GyroCalibration:
    """What one flight learnt of its gyro."""

    matrix: tuple[float, ...]
    """``M``, 9 values row-major (fractions): the part reads ``(I + M) w + b``."""
    matrix_std: tuple[float, ...]
    """1-sigma of each element (0: not estimated in that flight)."""
    temp_rad_s_per_c: tuple[float, float, float]
    temp_std_rad_s_per_c: tuple[float, float, float]
    flight_s: float = math.nan
    """Estimator time the log covers, s (NaN when not from a log)."""


def next_flight_params(cal: GyroCalibration, defaults: Mapping[str, float],
                       prefix: str = "EST") -> dict[str, float]:
    """The parameters that start the next flight from ``cal``.

    The priors narrow to ``PRIOR_SCALE`` times the learnt 1-sigma (the largest over the
    elements), never below the floors nor above ``defaults`` (the priors the flight that
    learnt it started from: ``GS_STD``, ``GB_TEMP`` without prefix). A term that flight did
    not estimate (1-sigma 0) keeps its default prior.
    """
    out = {f"{prefix}_{name}": float(v) for name, v in zip(GYRO_MATRIX_PARAMS, cal.matrix,
                                                            strict=True)}
    out.update({f"{prefix}_{name}": float(v) for name, v in zip(
        GYRO_TEMP_PARAMS, cal.temp_rad_s_per_c, strict=True)})
    gs_default = float(defaults.get("GS_STD", 0.0))
    gs_learnt = max(cal.matrix_std)
    if gs_learnt > 0.0 and gs_default > 0.0:
        out[f"{prefix}_GS_STD"] = min(gs_default, max(MIN_GS_STD, PRIOR_SCALE * gs_learnt))
    gt_default = float(defaults.get("GB_TEMP", 0.0))
    gt_learnt = max(cal.temp_std_rad_s_per_c)
    if gt_learnt > 0.0 and gt_default > 0.0:
        out[f"{prefix}_GB_TEMP"] = min(gt_default,
                                       max(MIN_GB_TEMP_RAD_S_PER_C, PRIOR_SCALE * gt_learnt))
    return out


def calibration_from_row(values: Sequence[float], flight_s: float = math.nan) -> GyroCalibration:
    """A calibration from one ``FMT_CAL`` record's 24 values (``CAL_COLUMNS`` order)."""
    v = [float(x) for x in values]
    if len(v) != 24:
        raise ValueError(f"a calibration record has 24 values, got {len(v)}")
    return GyroCalibration(tuple(v[0:9]), tuple(v[9:18]), (v[18], v[19], v[20]),
                           (v[21], v[22], v[23]), flight_s)


def learnt_from_log(path: str | os.PathLike[str]) -> GyroCalibration:
    """The last calibration record of an ``estimator.bin`` (or of a flight directory's).

    Raises :class:`CalibrationLogError` naming the file when it cannot be read, holds no
    calibration record (a log from before the records existed, or a flight without GPS),
    covers less than ``MIN_FLIGHT_S`` of estimator time, or its values are not finite.
    """
    from companion.estimation.logformats import CAL_COLUMNS, FMT_CAL
    from companion.logs.reader import read_log
    from companion.logs.streams import LogFormatError

    p = os.fspath(path)
    if os.path.isdir(p):
        p = os.path.join(p, "estimator.bin")
    try:
        lf = read_log(p, salvage=True)
    except FileNotFoundError:
        raise CalibrationLogError(f"{p}: no such file") from None
    except (OSError, LogFormatError) as exc:
        raise CalibrationLogError(f"{p}: cannot be read: {exc}") from None
    if FMT_CAL not in lf.indexes:
        raise CalibrationLogError(
            f"{p}: no calibration records (format {FMT_CAL}): not an estimator log, a log "
            "written before they existed, or a flight in which the GPS was never fused")
    try:
        data = lf.data(FMT_CAL)
        t_ns = lf.time_ns(FMT_CAL)
    except ValueError as exc:
        raise CalibrationLogError(str(exc)) from None
    names = data.dtype.names or ()
    if len(data) == 0 or tuple(names[-len(CAL_COLUMNS):]) != tuple(CAL_COLUMNS):
        raise CalibrationLogError(f"{p}: format {FMT_CAL} is not a calibration record "
                                  f"(columns {', '.join(names)})")
    flight_s = float(t_ns[-1] - t_ns[0]) / 1e9 if len(t_ns) else 0.0
    if flight_s < MIN_FLIGHT_S:
        raise CalibrationLogError(
            f"{p}: the calibration records cover {flight_s:.0f} s of flight; at least "
            f"{MIN_FLIGHT_S:.0f} s (turns both ways) are needed to learn from")
    row = [float(data[name][-1]) for name in CAL_COLUMNS]
    if not all(math.isfinite(v) for v in row):
        raise CalibrationLogError(f"{p}: the last calibration record holds a non-finite value")
    return calibration_from_row(row, flight_s)
