"""`companion sim --campaign SPEC --jobs J`: many simulated flights, one process each.

Researchers fly campaigns (seeds, wind, aircraft, sensor settings, parameter sets), and every
flight must be reproducible on its own: each one is a plain `companion sim` process with its own
flight directory and its own parameter file, so a flight of interest is re-flown by copying
its command line from `campaign.json`. Flights are lockstep by default (deterministic, as fast
as one core computes them); J flights run at a time.

The specification is TOML (or JSON with the same structure). Top-level keys are defaults for
every flight, `[grid]` gives lists whose Cartesian product is flown, and `[[flight]]` tables add
single flights:

    duration_s = 300
    scenario = "mixed"
    [grid]
    seed = [1, 2, 3]
    wind = [[0, 0, 0], [0, 8, 0]]
    [[flight]]
    seed = 100
    params = { CTL_ROLL_KP = 0.8 }

The campaign directory then holds `flights/` (one flight directory each), `params/` (each
flight's parameter file), `campaign.json` (every flight's settings, command, exit code, flight
directory and figures) and `dataset/`, the Parquet dataset of `companion logs export --dataset`
that `companion logs query` reads.
"""

from __future__ import annotations

import itertools
import json
import logging
import signal
import subprocess
import sys
import threading
import time
import tomllib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from companion.core.config import Config
from companion.core.files import write_json_bounded
from companion.core.params import ParamError
from companion.sim.faults import FAULT_KINDS

log = logging.getLogger(__name__)

__all__ = ["CampaignError", "FlightSpec", "load_campaign", "run_campaign"]

KEYS: dict[str, Any] = {
    "scenario": str, "seed": int, "aircraft": str, "wind": list, "gps_latency_s": (int, float),
    "duration_s": (int, float), "faults": list, "vanish": list, "thread_faults": list,
    "no_noise": bool, "no_level_cal": bool, "params": dict, "lockstep": bool, "speed": (int, float),
    "imu_profile": str, "gps_profile": str, "turbulence": str, "horizon_camera": str,
}
"""What a flight may set, with its type (`wind` is [N, E, D] in m/s)."""
_FAULT_KEYS = {kind.key for kind in FAULT_KINDS}
DEFAULTS: dict[str, Any] = {"scenario": "mixed", "seed": 0, "aircraft": "c172p",
                            "wind": [0.0, 0.0, 0.0], "duration_s": 60.0, "lockstep": True}
FLIGHT_MARGIN_S = 120.0  # host seconds a flight may take beyond its simulated duration


class CampaignError(ValueError):
    """A specification that cannot be flown; the message names the file and the entry."""


@dataclass
class FlightSpec:
    """One flight of a campaign: its settings and, once flown, what came of it."""

    index: int
    settings: dict[str, Any]
    command: list[str] = field(default_factory=list)
    exit_code: int | None = None
    flight_dir: str | None = None
    wall_s: float | None = None
    summary: dict[str, Any] = field(default_factory=dict)
    error: str = ""

    def record(self) -> dict[str, Any]:
        threads = self.summary.get("threads") or []
        return {
            "index": self.index, "settings": self.settings, "command": self.command,
            "exit_code": self.exit_code, "flight_dir": self.flight_dir, "wall_s": self.wall_s,
            "stop_reason": self.summary.get("stop_reason"),
            "restarts": sum(int(t.get("restarts") or 0) for t in threads),
            "failed_threads": [t.get("name") for t in threads if t.get("failed")],
            "speed": (self.summary.get("lockstep") or {}).get("speed"),
            "error": self.error,
        }


def load_campaign(path: Path) -> list[FlightSpec]:
    """The flights a specification describes, each checked (unknown keys, wrong types, unknown
    parameters or values out of range) before anything flies."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise CampaignError(f"{path}: {exc.strerror or exc}") from None
    try:
        spec = json.loads(text) if path.suffix == ".json" else tomllib.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise CampaignError(f"{path}: {exc}") from None
    if not isinstance(spec, dict):
        raise CampaignError(f"{path}: the specification must be a table of keys")
    grid = spec.pop("grid", None)
    singles = spec.pop("flight", None)
    base = {**DEFAULTS, **_checked(spec, f"{path}: top level")}
    flights: list[dict[str, Any]] = []
    if grid is not None:
        if not isinstance(grid, dict) or not grid:
            raise CampaignError(f"{path}: [grid] must be a table of lists")
        for key, values in grid.items():
            if not isinstance(values, list) or not values:
                raise CampaignError(f"{path}: [grid] {key}: expected a non-empty list")
        keys = list(grid)
        for combo in itertools.product(*(grid[k] for k in keys)):
            flights.append({**base, **_checked(dict(zip(keys, combo, strict=True)),
                                               f"{path}: [grid]")})
    if singles is not None:
        if not isinstance(singles, list):
            raise CampaignError(f"{path}: [[flight]] must be a list of tables")
        for i, single in enumerate(singles, start=1):
            if not isinstance(single, dict):
                raise CampaignError(f"{path}: [[flight]] #{i}: expected a table")
            flights.append({**base, **_checked(single, f"{path}: [[flight]] #{i}")})
    if not flights:
        raise CampaignError(f"{path}: no flights (give a [grid] or [[flight]] tables)")
    _check_params(flights, path)
    return [FlightSpec(i, f) for i, f in enumerate(flights, start=1)]


def _checked(table: dict[str, Any], where: str) -> dict[str, Any]:
    for key, value in table.items():
        kind = KEYS.get(key)
        if kind is None:
            raise CampaignError(f"{where}: unknown key {key!r} (known: {', '.join(KEYS)})")
        if isinstance(value, bool) and kind is not bool:
            raise CampaignError(f"{where}: {key} = {value!r}: expected {_name(kind)}")
        if not isinstance(value, kind):
            raise CampaignError(f"{where}: {key} = {value!r}: expected {_name(kind)}")
        if key == "wind" and (len(value) != 3 or not all(
                isinstance(w, int | float) and not isinstance(w, bool) for w in value)):
            raise CampaignError(f"{where}: wind = {value!r}: expected [N, E, D] in m/s")
        if key in _FAULT_KEYS and not all(isinstance(v, str) for v in value):
            raise CampaignError(f"{where}: {key}: expected a list of strings")
        if key == "horizon_camera":
            from companion.sim.world import HORIZON_CAMERA_CHOICES

            if value not in HORIZON_CAMERA_CHOICES:
                raise CampaignError(f"{where}: horizon_camera = {value!r}: one of "
                                    f"{', '.join(HORIZON_CAMERA_CHOICES)}")
        if key in ("imu_profile", "gps_profile", "turbulence"):
            from companion.sim.profiles import gps_profile, imu_profile, turbulence_severity

            check = {"imu_profile": imu_profile, "gps_profile": gps_profile,
                     "turbulence": turbulence_severity}[key]
            try:
                check(value)
            except ValueError as exc:
                raise CampaignError(f"{where}: {key}: {exc}") from None
    return dict(table)


def _name(kind: Any) -> str:
    kinds = kind if isinstance(kind, tuple) else (kind,)
    return " or ".join(k.__name__ for k in kinds)


def _check_params(flights: list[dict[str, Any]], path: Path) -> None:
    """Parameter overrides checked against the runtime's own declarations and rules."""
    from companion.runtime import declared_registry

    registry = declared_registry(Config())
    for i, flight in enumerate(flights, start=1):
        params = flight.get("params") or {}
        try:
            registry.check(params)
        except ParamError as exc:
            raise CampaignError(f"{path}: flight {i}: params: {exc}") from None


def flight_command(spec: FlightSpec, campaign_dir: Path) -> list[str]:
    s = spec.settings
    params_file = campaign_dir / "params" / f"{spec.index:04d}.parm"
    cmd = [sys.executable, "-m", "companion", "sim", "--json",
           "--log-dir", str(campaign_dir / "flights"), "--params-file", str(params_file),
           "--scenario", str(s["scenario"]), "--seed", str(s["seed"]),
           "--aircraft", str(s["aircraft"]), "--duration", repr(float(s["duration_s"])),
           "--wind", *(repr(float(w)) for w in s["wind"]),
           "--mavlink", "none"]
    camera = str(s.get("horizon_camera", "off"))
    if camera != "off":
        cmd += ["--horizon-camera", camera]
    if camera != "off" and not s.get("lockstep", True):
        # the camera's fixes travel on the legacy command port: any free one, on loopback
        cmd += ["--legacy-listen", "0"]
    else:
        cmd.append("--no-legacy")
    if s.get("lockstep", True):
        cmd.append("--lockstep")
    elif s.get("speed"):
        cmd += ["--speed", repr(float(s["speed"]))]
    if "gps_latency_s" in s:
        cmd += ["--gps-latency", repr(float(s["gps_latency_s"]))]
    if s.get("no_noise"):
        cmd.append("--no-noise")
    if s.get("no_level_cal"):
        cmd.append("--no-level-cal")
    for key, option in (("imu_profile", "--imu-profile"), ("gps_profile", "--gps-profile"),
                        ("turbulence", "--turbulence")):
        if key in s:
            cmd += [option, str(s[key])]
    for kind in FAULT_KINDS:
        for value in s.get(kind.key) or ():
            cmd += [kind.option, value]
    return cmd


def run_campaign(specs: list[FlightSpec], campaign_dir: Path, jobs: int, *,
                 spec_path: Path | None = None, dataset: bool = True,
                 progress: Callable[[FlightSpec, int, int], None] | None = None
                 ) -> dict[str, Any]:
    """Fly every flight, `jobs` at a time; write campaign.json (and the dataset); return it."""
    if jobs < 1:
        raise CampaignError(f"--jobs {jobs}: at least 1")
    (campaign_dir / "params").mkdir(parents=True, exist_ok=True)
    (campaign_dir / "flights").mkdir(parents=True, exist_ok=True)
    for spec in specs:
        params = spec.settings.get("params") or {}
        (campaign_dir / "params" / f"{spec.index:04d}.parm").write_text(
            "".join(f"{name} {value}\n" for name, value in params.items()), encoding="utf-8")
        spec.command = flight_command(spec, campaign_dir)
    stop = threading.Event()
    running: set[subprocess.Popen[str]] = set()
    lock = threading.Lock()
    done = [0]

    def fly(spec: FlightSpec) -> None:
        if stop.is_set():
            spec.error = "not flown (campaign interrupted)"
            return
        t0 = time.monotonic()
        timeout = float(spec.settings["duration_s"]) + FLIGHT_MARGIN_S
        proc = subprocess.Popen(spec.command, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True)
        with lock:
            running.add(proc)
        try:
            out, err = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
            spec.error = f"no result within {timeout:.0f} s: killed"
        finally:
            with lock:
                running.discard(proc)
        spec.wall_s = round(time.monotonic() - t0, 2)
        spec.exit_code = proc.returncode
        try:
            spec.summary = json.loads(out) if out.strip() else {}
        except json.JSONDecodeError:
            spec.summary = {}
        spec.flight_dir = spec.summary.get("flight_dir")
        if proc.returncode != 0 and not spec.error:
            spec.error = (err.strip().splitlines() or ["(no message)"])[-1][:300]
        with lock:
            done[0] += 1
            n = done[0]
        if progress is not None:
            progress(spec, n, len(specs))

    t0 = time.monotonic()
    started = datetime.now(UTC).isoformat()
    pool = ThreadPoolExecutor(max_workers=jobs, thread_name_prefix="campaign")
    futures = [pool.submit(fly, s) for s in specs]
    try:
        for f in futures:
            f.result()
    except KeyboardInterrupt:
        stop.set()
        with lock:
            for proc in running:
                proc.send_signal(signal.SIGINT)
        for f in futures:
            f.result()
    finally:
        pool.shutdown(wait=True)
    wall_s = time.monotonic() - t0
    flown = [s for s in specs if s.exit_code == 0]
    sim_s = sum(float(s.settings["duration_s"]) for s in flown)
    result: dict[str, Any] = {
        "specification": str(spec_path) if spec_path else None,
        "started_utc": started, "jobs": jobs, "flights": len(specs), "ok": len(flown),
        "failed": len(specs) - len(flown), "wall_s": round(wall_s, 2),
        "simulated_s": sim_s, "speed": round(sim_s / wall_s, 1) if wall_s > 0 else None,
        "restarts": sum(s.record()["restarts"] for s in specs),
        "runs": [s.record() for s in specs],
    }
    if dataset:
        result["dataset"] = _export(specs, campaign_dir / "dataset")
    write_json_bounded(campaign_dir / "campaign.json", result, 5.0)
    return result


def _export(specs: list[FlightSpec], dataset_dir: Path) -> dict[str, Any]:
    from companion.logs.dataset import export_flight

    t0 = time.monotonic()
    exported, problems = 0, []
    for spec in specs:
        if not spec.flight_dir:
            continue
        try:
            out = export_flight(Path(spec.flight_dir), dataset_dir)
        except OSError as exc:
            problems.append(f"flight {spec.index}: {exc}")
            continue
        exported += 1
        problems += [f"flight {spec.index}: {p}" for p in out.problems]
    return {"dir": str(dataset_dir), "flights": exported, "problems": problems,
            "export_s": round(time.monotonic() - t0, 2)}
