"""The figures a campaign (and a parameter search) judges one flight by.

A flight's summary.json says how the runtime fared (restarts, speed, stop reason) but not how
well it estimated or flew; those come from its logs against the simulator's truth. They are
computed once, on the node that flew the flight, and kept in its record, so a search reads a
number and not a flight directory that may be in a bucket.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["METRICS", "flight_metrics", "metric_value"]

log = logging.getLogger(__name__)

METRICS: dict[str, str] = {
    "roll_rmse_deg": "estimated roll against the truth, RMS over the flight",
    "pitch_rmse_deg": "estimated pitch against the truth, RMS over the flight",
    "inclination_rmse_deg": "estimated tilt (roll and pitch together) against the truth, RMS",
    "roll_tracking_rmse_deg": "true roll against the control law's roll set-point, RMS while "
                              "the law is engaged",
}
"""Derived metrics by name; any other metric is a dotted path into the flight's summary.json
(e.g. `lockstep.speed`, `simulator.level_calibration.level_error_roll_deg`)."""

SUMMARY_ROOTS = ("stop_reason", "host_seconds", "simulator", "lockstep", "logs", "sensors")
"""The summary.json sections a metric path may start with (checked before anything flies)."""


def check_metric(name: str) -> str | None:
    """Why `name` is not a metric a flight can give, or None when it is."""
    if name in METRICS or name.split(".", 1)[0] in SUMMARY_ROOTS:
        return None
    return (f"unknown metric {name!r}: one of {', '.join(METRICS)}, or a path into the "
            f"flight's summary.json under {', '.join(SUMMARY_ROOTS)}")


def metric_value(record: dict[str, Any], name: str) -> float | None:
    """The metric of a flown flight, from its record, or None when the flight does not have it."""
    metrics = record.get("metrics") or {}
    if name in METRICS:
        value = metrics.get(name)
    else:
        value = (metrics.get("summary") or {}).get(name)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        return None
    return float(value)


def flight_metrics(flight_dir: Path, summary: dict[str, Any]) -> dict[str, Any]:
    """Every derived metric of the flight (NaN when its logs cannot give it) and the flat numeric
    figures of its summary under "summary"."""
    out: dict[str, Any] = {"summary": _flat_numbers(summary)}
    try:
        out.update(_attitude_errors(flight_dir))
    except (OSError, ValueError, KeyError) as exc:
        log.warning("%s: no attitude metrics: %s", flight_dir, exc)
    return out


def _flat_numbers(tree: dict[str, Any], prefix: str = "") -> dict[str, float]:
    flat: dict[str, float] = {}
    for key, value in tree.items():
        path = f"{prefix}{key}"
        if isinstance(value, dict):
            flat.update(_flat_numbers(value, path + "."))
        elif isinstance(value, int | float) and not isinstance(value, bool):
            flat[path] = float(value)
    return flat


def _rms_deg(err_rad: np.ndarray) -> float:
    return round(math.degrees(float(np.sqrt(np.mean(np.square(err_rad))))), 6) \
        if err_rad.size else math.nan


def _attitude_errors(flight_dir: Path) -> dict[str, float]:
    from companion.report.analysis import interp_angle_at
    from companion.report.flight import load_flight

    fd = load_flight(flight_dir)
    truth = fd.block("truth", 1, ("roll_rad", "pitch_rad"))
    est = fd.block("estimator", 1, ("roll_rad", "pitch_rad", "aligned"))
    ctl = fd.block("control", 1, ("enabled", "roll_sp_rad"))
    out = {name: math.nan for name in METRICS}
    if truth is None:
        return out
    t_truth = np.asarray(truth["time_s"], dtype=np.float64)
    if est is not None:
        t_est = np.asarray(est["time_s"], dtype=np.float64)
        keep = est["aligned"] != 0
        if keep.any():
            roll_t = interp_angle_at(t_truth, truth["roll_rad"], t_est[keep])
            pitch_t = interp_angle_at(t_truth, truth["pitch_rad"], t_est[keep])
            d_roll = _wrap(est["roll_rad"][keep] - roll_t)
            d_pitch = _wrap(est["pitch_rad"][keep] - pitch_t)
            out["roll_rmse_deg"] = _rms_deg(d_roll)
            out["pitch_rmse_deg"] = _rms_deg(d_pitch)
            out["inclination_rmse_deg"] = _rms_deg(np.hypot(d_roll, d_pitch))
    if ctl is not None:
        engaged = ctl["enabled"] != 0
        if engaged.any():
            t_ctl = np.asarray(ctl["time_s"], dtype=np.float64)[engaged]
            roll_t = interp_angle_at(t_truth, truth["roll_rad"], t_ctl)
            out["roll_tracking_rmse_deg"] = _rms_deg(_wrap(roll_t - ctl["roll_sp_rad"][engaged]))
    return out


def _wrap(a: np.ndarray) -> np.ndarray:
    return np.asarray((np.asarray(a, dtype=np.float64) + math.pi) % (2 * math.pi) - math.pi)
