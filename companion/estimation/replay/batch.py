"""Many logs in one command: which files, where each one's output goes, one table row per log.

`companion estimation replay DIR... --table out.csv` finds every log under the directories
given (recursively, by suffix), replays each into its own subdirectory of the output directory,
and writes one CSV row per log, a log that cannot be read included (its row says why), so that
a collection of real logs is scored in one go and a bad file costs its own row only.
"""

from __future__ import annotations

import csv
from collections.abc import Iterable
from pathlib import Path
from typing import Any

LOG_SUFFIXES = (".bin", ".ulg", ".tlog")
"""What a directory's logs are called (any case: ArduPilot's SD card writes ``.BIN``)."""

REFERENCE_ORDER = ("ATT", "AHR2", "XKF1", "NKF1", "vehicle_attitude",
                   "vehicle_attitude_groundtruth")
"""Columns of the references in this order first; any other reference follows by name."""

BASE_COLUMNS = ["source", "format", "status", "duration_s", "imu_source", "imu_rate_hz",
                "gps_source", "gps_fixes", "estimator", "imu_filter", "estimator_reason",
                "started_at_s", "heading_from", "references", "notes"]
METRICS = (("inclination_deg", "incl"), ("roll_deg", "roll"), ("pitch_deg", "pitch"),
           ("yaw_deg", "yaw"))


def find_logs(paths: Iterable[Path]) -> list[Path]:
    """Files as given; directories searched recursively for `LOG_SUFFIXES`, sorted, each file
    once."""
    out: list[Path] = []
    seen: set[Path] = set()
    for p in paths:
        found = (sorted(f for f in p.rglob("*") if f.is_file()
                        and f.suffix.lower() in LOG_SUFFIXES) if p.is_dir() else [p])
        for f in found:
            key = f.resolve()
            if key not in seen:
                seen.add(key)
                out.append(f)
    return out


def output_dirs(logs: list[Path], root: Path) -> dict[Path, Path]:
    """Each log's output directory: ``<root>/<log stem>-replay``, with ``-2``, ``-3``... when
    two logs share a stem (``1.BIN`` in several folders), in the order given."""
    out: dict[Path, Path] = {}
    used: set[str] = set()
    for log in logs:
        base = f"{log.stem}-replay"
        name, n = base, 1
        while name.lower() in used:
            n += 1
            name = f"{base}-{n}"
        used.add(name.lower())
        out[log] = root / name
    return out


def table_row(summary: dict[str, Any] | None, source: Path, error: str | None = None
              ) -> dict[str, Any]:
    """One log's row: what ran, the differences (RMSE, deg) from each reference, the notes."""
    row: dict[str, Any] = {"source": str(source)}
    if summary is None:
        row.update(status="error", notes=error or "")
        return row
    est = summary.get("estimate", {})
    imu = summary.get("timelines", {}).get("imu", {})
    gps = summary.get("timelines", {}).get("gps") or {}
    start = summary.get("start") or {}
    span = (start.get("imu_span_s") or [None, None])[1]
    row.update(
        format=summary.get("format"), status="partial" if summary["estimator"] == "none"
        else "ok", duration_s=span, imu_source=summary.get("imu_source"),
        imu_rate_hz=imu.get("rate_hz"), gps_source=summary.get("gps_source"),
        gps_fixes=est.get("gps_fixes_offered", gps.get("samples_used")),
        estimator=summary.get("estimator"), imu_filter=summary.get("imu_filter"),
        estimator_reason=summary.get("estimator_reason"),
        started_at_s=start.get("started_at_s"), heading_from=start.get("heading_from"),
        references=" ".join(summary.get("comparisons", {})),
        notes=" | ".join(summary.get("notes", [])))
    for ref, metrics in summary.get("comparisons", {}).items():
        for key, short in METRICS:
            m = metrics.get(key) or {}
            row[f"{ref}_{short}_rmse_deg"] = m.get("rmse")
        row[f"{ref}_samples"] = metrics.get("samples_compared")
    return row


def write_table(rows: list[dict[str, Any]], path: Path) -> Path:
    """The rows as CSV, the references' columns in `REFERENCE_ORDER` then by name."""
    refs: list[str] = []
    for row in rows:
        for key in row:
            if key.endswith("_samples") and key[: -len("_samples")] not in refs:
                refs.append(key[: -len("_samples")])
    refs.sort(key=lambda r: (REFERENCE_ORDER.index(r) if r in REFERENCE_ORDER
                             else len(REFERENCE_ORDER), r))
    columns = list(BASE_COLUMNS)
    for ref in refs:
        columns += [f"{ref}_{short}_rmse_deg" for _, short in METRICS] + [f"{ref}_samples"]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=columns, extrasaction="ignore")
        w.writeheader()
        for row in rows:
            w.writerow({k: "" if v is None else v for k, v in row.items()})
    tmp.replace(path)
    return path
