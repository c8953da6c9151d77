"""A campaign's specification: the flights a TOML (or JSON) file describes, checked before
anything flies, and the command line that flies each one on its own.

Kept apart from the running of a campaign so that a Ray worker, a search and the command line
read one definition of a flight.
"""

from __future__ import annotations

import itertools
import json
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.core.config import Config
from companion.core.params import ParamError
from companion.sim.faults import FAULT_KINDS

__all__ = ["CampaignError", "FlightSpec", "flight_command", "load_campaign", "read_spec"]

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
    """One flight of a campaign: its settings and, once flown, its record (what the flight's
    completion marker holds: command, exit code, node, tries, figures)."""

    index: int
    settings: dict[str, Any]
    result: dict[str, Any] | None = None

    @property
    def name(self) -> str:
        """The flight's directory name in the campaign: its index, so that a re-flown flight
        lands where (and exports as) the first attempt would have."""
        return f"{self.index:04d}"

    def record(self) -> dict[str, Any]:
        base: dict[str, Any] = {"index": self.index, "settings": self.settings}
        if self.result is None:
            return {**base, "exit_code": None, "error": "not flown", "tries": 0, "node": None,
                    "restarts": 0, "wall_s": None}
        return {**base, **self.result}


def read_spec(path: Path) -> dict[str, Any]:
    """The specification's table, or a CampaignError naming the file and what is wrong."""
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
    return spec


def base_settings(spec: dict[str, Any], path: Path) -> dict[str, Any]:
    """The top-level keys (every flight's defaults), checked."""
    top = {k: v for k, v in spec.items() if k not in ("grid", "flight", "search")}
    return {**DEFAULTS, **_checked(top, f"{path}: top level")}


def load_campaign(path: Path) -> list[FlightSpec]:
    """The flights a specification describes, each checked (unknown keys, wrong types, unknown
    parameters or values out of range) before anything flies. A `[search]` table is read by
    `companion.sim.search` and ignored here."""
    spec = read_spec(path)
    grid = spec.pop("grid", None)
    singles = spec.pop("flight", None)
    base = base_settings(spec, path)
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
    check_params(flights, path)
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


def check_params(flights: list[dict[str, Any]], path: Path) -> None:
    """Parameter overrides checked against the runtime's own declarations and rules."""
    from companion.runtime import declared_registry

    registry = declared_registry(Config())
    for i, flight in enumerate(flights, start=1):
        params = flight.get("params") or {}
        try:
            registry.check(params)
        except ParamError as exc:
            raise CampaignError(f"{path}: flight {i}: params: {exc}") from None


def flight_command(settings: dict[str, Any], log_dir: str, params_file: str) -> list[str]:
    """The `companion sim` command line that flies one flight on its own, into `log_dir`, with
    the overrides of `params_file`: kept in campaign.json so any flight is re-flown by hand."""
    s = settings
    cmd = [sys.executable, "-m", "companion", "sim", "--json",
           "--log-dir", log_dir, "--params-file", params_file,
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


