"""What a replay writes: `estimate.bin` (the project's log format), `summary.json`, `replay.png`.

`estimate.bin` holds our estimate and the flight controller's side by side, so every tool of
`companion logs` (convert, info, export, query) reads a replay like a flight:

| format | columns |
| --- | --- |
| 1 | ours: roll_rad, pitch_rad, yaw_rad, north_m, east_m, down_m, vn_m_s, ve_m_s, vd_m_s, aligned, faults (NaN position/velocity for the IMU-only filter) |
| 2.. | theirs, one per reference in summary order: `<name>_roll_rad`, `<name>_pitch_rad`, `<name>_yaw_rad` |

Record times are the log's clock (the flight controller's boot time, after the replay's clock
corrections), in the record TIME.
"""

from __future__ import annotations

import logging
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from companion.estimation.replay.runner import ReplayResult

log = logging.getLogger(__name__)

FMT_OURS = 1
OURS_COLUMNS = ["roll_rad", "pitch_rad", "yaw_rad", "north_m", "east_m", "down_m", "vn_m_s",
                "ve_m_s", "vd_m_s", "aligned", "faults"]
OURS_FORMAT = ",".join(["%.6f"] * 3 + ["%.3f"] * 6) + ",%hhu,%u"
REF_FORMAT = "%.6f,%.6f,%.6f"
ESTIMATOR_LABELS = {"eskf": "ESKF (GPS/INS, EstimatorCore)",
                    "attitude": "IMU-only (no GPS: heading arbitrary)",
                    "none": "none (no IMU samples)"}


def estimator_label(result: ReplayResult) -> str:
    """What ran, in words: the IMU-only filter by its registry name."""
    if result.estimator == "attitude":
        return f"IMU-only {result.imu_filter} (no GPS: heading arbitrary)"
    return ESTIMATOR_LABELS[result.estimator]


def _label(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_]", "_", name)


def write_estimate_log(result: ReplayResult, out_dir: Path) -> Path:
    """Write `estimate.bin` (replacing an earlier one) through the flight's log writer."""
    from companion.logs.writer import LogService

    path = out_dir / "estimate.bin"
    path.unlink(missing_ok=True)
    est = result.estimate
    now = [int(est.t_us[0]) * 1000 if len(est.t_us) else result.t0_us * 1000]
    service = LogService(out_dir, writer_thread=False, capacity_records=1 << 16,
                         clock_ns=lambda: now[0])
    service.start()
    try:
        tlog = service.open("estimate")
        tlog.define(FMT_OURS, OURS_FORMAT, OURS_COLUMNS)
        for i, comp in enumerate(result.comparisons):
            lab = _label(comp.name)
            tlog.define(FMT_OURS + 1 + i, REF_FORMAT,
                        [f"{lab}_roll_rad", f"{lab}_pitch_rad", f"{lab}_yaw_rad"])
        tlog.begin()
        rows = np.column_stack([est.euler_rad, est.pos_ned_m, est.vel_ned_m_s]).tolist()
        refs = [c.ref_euler_rad.tolist() for c in result.comparisons]
        for k, t_us in enumerate(est.t_us.tolist()):
            t_ns = t_us * 1000
            tlog.log(FMT_OURS, *rows[k], int(est.aligned[k]), int(est.faults[k]), t_ns=t_ns)
            for i, ref in enumerate(refs):
                if not math.isnan(ref[k][0]):
                    tlog.log(FMT_OURS + 1 + i, *ref[k], t_ns=t_ns)
            if k % 4096 == 4095:
                service.drain()
        if len(est.t_us):
            now[0] = int(est.t_us[-1]) * 1000
        tlog.end()
        service.drain()
    finally:
        service.close()
    return path


def summary_dict(result: ReplayResult, files: dict[str, str]) -> dict[str, Any]:
    """Everything the replay found, JSON-ready."""
    f = result.flight
    est = result.estimate
    span = (float(est.t_us[-1] - est.t_us[0]) / 1e6) if len(est.t_us) else 0.0
    out: dict[str, Any] = {
        "log": str(f.path), "format": f.kind, "log_info": f.info,
        "estimator": result.estimator, "estimator_label": estimator_label(result),
        "estimator_reason": result.estimator_reason, "imu_filter": result.imu_filter or None,
        "start": result.start.as_dict(),
        "imu_source": f.imu.source, "gps_source": f.gps.source if f.gps is not None else None,
        "estimate": {"samples": len(est.t_us), "span_s": round(span, 3),
                     "start_s": round((int(est.t_us[0]) - result.t0_us) / 1e6, 3)
                     if len(est.t_us) else None, **result.stats},
        "timelines": {k: v.as_dict() for k, v in result.timelines.items()},
        "comparisons": {c.name: c.metrics for c in result.comparisons},
        "streams": {"1": "ours"} | {str(2 + i): c.name for i, c in enumerate(result.comparisons)},
        "damage": f.damage, "notes": result.notes, "files": files,
        "run_time_s": round(result.run_time_s, 3)}
    return _plain(out)


def _plain(x: Any) -> Any:
    """numpy scalars to Python numbers, NaN to None (strict JSON)."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def write_figure(result: ReplayResult, path: Path) -> Path:
    """Roll, pitch and yaw, ours against each reference, and the inclination difference."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    est = result.estimate
    t_s = (est.t_us - result.t0_us) / 1e6

    def wrapped_deg(a_deg: np.ndarray) -> np.ndarray:
        """Into [-180, 180), with a break (NaN) where a line would cross the whole plot."""
        w = (a_deg + 180.0) % 360.0 - 180.0
        jumps = np.flatnonzero(np.abs(np.diff(w)) > 180.0)
        return np.insert(w, jumps + 1, np.nan)

    def broken_t(a_deg: np.ndarray) -> np.ndarray:
        w = (a_deg + 180.0) % 360.0 - 180.0
        jumps = np.flatnonzero(np.abs(np.diff(w)) > 180.0)
        return np.insert(t_s.astype(float), jumps + 1, np.nan)

    fig, axes = plt.subplots(4, 1, figsize=(11, 10), sharex=True)
    names = ("roll", "pitch", "yaw")
    for a, name in enumerate(names):
        ax = axes[a]
        ours = np.degrees(est.euler_rad[:, a])
        if a == 2 and result.estimator == "eskf":
            ours = np.where(est.aligned, ours, np.nan)
        if a == 2:
            ax.plot(broken_t(ours), wrapped_deg(ours), lw=0.9, label=f"ours ({result.estimator})")
        else:
            ax.plot(t_s, ours, lw=0.9, label=f"ours ({result.estimator})")
        for comp in result.comparisons:
            ref = np.degrees(comp.ref_euler_rad[:, a])
            off = comp.metrics.get("yaw_offset_removed_deg") if a == 2 else None
            label = comp.name + (f" (+{off:.1f}° offset)" if off is not None else "")
            if a == 2:
                ref = ref + (off or 0.0)
                ax.plot(broken_t(ref), wrapped_deg(ref), lw=0.9, alpha=0.8, label=label)
            else:
                ax.plot(t_s, ref, lw=0.9, alpha=0.8, label=label)
        ax.set_ylabel(f"{name} (deg)")
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    ax = axes[3]
    for comp in result.comparisons:
        rmse = comp.metrics.get("inclination_deg", {}).get("rmse")
        ax.plot(t_s, comp.err_deg[:, 3], lw=0.9,
                label=f"vs {comp.name} (RMSE {rmse}°)" if rmse is not None else comp.name)
    ax.set_ylabel("inclination diff (deg)")
    ax.set_xlabel("time from the first IMU sample (s)")
    ax.grid(True, alpha=0.3)
    if result.comparisons:
        ax.legend(loc="upper right", fontsize=8)
    fig.suptitle(f"{result.flight.path.name}: {estimator_label(result)}",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
