"""Runtime configuration: one TOML file, every value overridable on the command line.

Settings are things that describe the installation (which port the IMU is on, where the ground
station listens); parameters (companion.core.params) are things an operator tunes in flight. A
setting changes only with a restart, which is why the two live apart.
"""

from __future__ import annotations

import dataclasses
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


class ConfigError(ValueError):
    """A bad configuration file or override; the message names the file and the key."""


@dataclass
class DeviceConfig:
    """One ``[devices.<name>]`` table. Which devices exist, and their defaults, is the vehicle
    table's fact (`companion.vehicle`), handed to `load_config`: this module knows no device."""

    port: str = ""  # device path, pseudo-terminal, or any pyserial URL (loop://, socket://)
    baud: int = 115200
    enabled: bool = True


@dataclass
class VehicleConfig:
    id: int = 1
    # Home (origin of the local NED frame): a surveyed launch point, or empty to take the first
    # good GPS fix. SITL sets it to the simulator's start point so truth and estimate share a frame.
    home: str = ""  # "lat_deg,lon_deg,alt_m"

    def home_lla(self) -> tuple[float, float, float] | None:
        """The configured home, or None; a malformed value is a ConfigError naming the key."""
        if not self.home.strip():
            return None
        try:
            lat, lon, alt = (float(v) for v in self.home.split(","))
        except ValueError:
            raise ConfigError(f"vehicle.home: expected 'lat_deg,lon_deg,alt_m', got {self.home!r}") from None
        if not (-90 <= lat <= 90 and -180 <= lon <= 360 and -1000 <= alt <= 100_000):
            # (NaN fails every comparison, so it is refused here too)
            raise ConfigError(f"vehicle.home: {self.home!r} is not a valid position "
                              "(latitude -90..90, longitude -180..360, altitude -1000..100000 m)")
        return lat, lon, alt


@dataclass
class LogsConfig:
    dir: str = "flights"
    enabled: bool = True


@dataclass
class ParamsConfig:
    file: str = "params.parm"  # where parameter changes persist; relative to the working dir


@dataclass
class MavlinkConfig:
    endpoints: list[str] = field(default_factory=lambda: ["udpout:127.0.0.1:14550"])
    key_file: str = ""  # MAVLink 2 signing key ("companion keys new"); empty = no signing
    allow_unsigned_reads: bool = True


@dataclass
class LegacyConfig:
    dest: str = "255.255.255.255:5501"
    listen: int = 5500
    bind: str = "0.0.0.0"  # address the command socket listens on
    allow: list[str] = field(default_factory=lambda: ["127.0.0.0/8"])
    enabled: bool = True


@dataclass
class RerunConfig:
    enabled: bool = False
    save: str = ""


@dataclass
class Config:
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    devices: dict[str, DeviceConfig] = field(default_factory=dict)
    """Keyed by device name; `companion.vehicle.fill_device_defaults` gives every device of
    the vehicle its row's defaults."""
    logs: LogsConfig = field(default_factory=LogsConfig)
    params: ParamsConfig = field(default_factory=ParamsConfig)
    mavlink: MavlinkConfig = field(default_factory=MavlinkConfig)
    legacy: LegacyConfig = field(default_factory=LegacyConfig)
    rerun: RerunConfig = field(default_factory=RerunConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def load_config(path: Path | None, devices: Mapping[str, DeviceConfig] | None = None,
                aliases: Mapping[str, str] | None = None) -> Config:
    """Read a TOML file over the defaults; unknown keys and wrong types are errors, by name.

    `devices` are the vehicle's devices with their defaults (`VehicleTable.device_defaults`):
    a ``[devices.<name>]`` table for another name is an error that lists them. None: the
    devices are not checked here (the caller fills and checks them against its table).
    `aliases`: top-level tables read as a device's (``[autopilot] url = ...`` is
    ``[devices.autopilot] port = ..., enabled = true``), see `given_devices`."""
    return load_config_given(path, devices, aliases)[0]


def load_config_given(path: Path | None, devices: Mapping[str, DeviceConfig] | None = None,
                      aliases: Mapping[str, str] | None = None) -> tuple[Config, set[str]]:
    """`load_config`, and the names of the devices the file configures itself (so that the
    caller can tell a device the user chose from one left at its defaults)."""
    cfg = Config()
    if devices is not None:
        cfg.devices = {name: dataclasses.replace(d) for name, d in devices.items()}
    if path is None:
        return cfg, set()
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte offset {exc.start})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    except RecursionError:
        raise ConfigError(f"{path}: values nested too deeply to read") from None
    _read_aliases(data, aliases or {}, str(path))
    _merge(cfg, data, str(path), "")
    given = data.get("devices", {})
    return cfg, set(given) if isinstance(given, dict) else set()


def _read_aliases(data: dict[str, Any], aliases: Mapping[str, str], where: str) -> None:
    """Rewrite each ``[<alias>]`` table of `data` as ``[devices.<device>]``: ``url`` is the
    port (a pymavlink connection string) and switches the device on; its other keys are the
    device's own. Both spellings for one device are an error naming both."""
    for alias, device in aliases.items():
        table = data.pop(alias, None)
        if table is None:
            continue
        if not isinstance(table, dict):
            raise ConfigError(f"{where}: '{alias}' must be a table")
        devices = data.setdefault("devices", {})
        if not isinstance(devices, dict):
            raise ConfigError(f"{where}: 'devices' must be a table")
        if device in devices:
            raise ConfigError(f"{where}: [{alias}] and [devices.{device}] both configure "
                              f"the {device}: keep one")
        settings = dict(table)
        if "url" in settings:
            if "port" in settings:
                raise ConfigError(f"{where}: [{alias}] has both 'url' and 'port': keep one")
            settings["port"] = settings.pop("url")
            settings.setdefault("enabled", True)
        devices[device] = settings


#: Settings that moved elsewhere: what a configuration still using them is told.
MOVED = {
    "mavlink.identity": "the identity is now chosen per link: add '?identity=generic|px4|"
                        "ardupilot' to each endpoint, e.g. 'udpout:127.0.0.1:14550?identity=px4' "
                        "(see docs/ground-stations.md)",
}


def _merge(obj: Any, data: dict[str, Any], where: str, prefix: str) -> None:
    fields = {f.name: f for f in dataclasses.fields(obj)}
    for key, value in data.items():
        dotted = f"{prefix}{key}"
        if dotted in MOVED:
            raise ConfigError(f"{where}: setting '{dotted}' was removed: {MOVED[dotted]}")
        if key not in fields:
            raise ConfigError(f"{where}: unknown setting '{dotted}' (known: {', '.join(fields)})")
        current = getattr(obj, key)
        if isinstance(current, dict):
            if not isinstance(value, dict):
                raise ConfigError(f"{where}: '{dotted}' must be a table")
            _merge_tables(current, value, where, dotted + ".")
        elif dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise ConfigError(f"{where}: '{dotted}' must be a table")
            _merge(current, value, where, dotted + ".")
        else:
            setattr(obj, key, _coerce(value, current, where, dotted))


def _merge_tables(tables: dict[str, Any], data: dict[str, Any], where: str, prefix: str) -> None:
    """``[devices.<name>]``: a name the vehicle has merges over its defaults; when the vehicle's
    devices were not given (`tables` empty), any name starts from `DeviceConfig`'s defaults."""
    checked = bool(tables)
    for name, value in data.items():
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: '{prefix}{name}' must be a table")
        if name not in tables:
            if checked:
                raise ConfigError(f"{where}: unknown device '{prefix}{name}' "
                                  f"(known: {', '.join(tables)})")
            tables[name] = DeviceConfig()
        _merge(tables[name], value, where, f"{prefix}{name}.")


def _coerce(value: Any, current: Any, where: str, dotted: str) -> Any:
    expected = type(current)
    if isinstance(current, bool):
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false", "1", "0", "yes", "no"):
            return value.lower() in ("true", "1", "yes")
    elif isinstance(current, int):
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, str):
            try:
                return int(value, 0)
            except ValueError:
                pass
    elif isinstance(current, list):
        if isinstance(value, list) and all(isinstance(v, str) for v in value):
            return list(value)
        if isinstance(value, str):
            return [v for v in value.split(",") if v]
    elif isinstance(current, str):
        if isinstance(value, str):
            return value
    raise ConfigError(f"{where}: '{dotted}' must be {expected.__name__}, got {value!r}")


def apply_override(cfg: Config, assignment: str) -> None:
    """Apply one `section.key=value` override from the command line."""
    if "=" not in assignment:
        raise ConfigError(f"--set {assignment!r}: expected section.key=value")
    dotted, value = assignment.split("=", 1)
    if dotted.strip() in MOVED:
        raise ConfigError(f"--set: setting '{dotted.strip()}' was removed: {MOVED[dotted.strip()]}")
    parts = dotted.strip().split(".")
    obj: Any = cfg
    for i, part in enumerate(parts):
        if isinstance(obj, dict) and i < len(parts) - 1:
            if part not in obj:
                raise ConfigError(f"--set: unknown setting '{'.'.join(parts[: i + 1])}' "
                                  f"(known: {', '.join(obj)})")
            obj = obj[part]
            continue
        if not dataclasses.is_dataclass(obj) or part not in {f.name for f in dataclasses.fields(obj)}:
            raise ConfigError(f"--set: unknown setting '{'.'.join(parts[: i + 1])}'")
        if i == len(parts) - 1:
            setattr(obj, part, _coerce(value, getattr(obj, part), "--set", dotted))
        else:
            obj = getattr(obj, part)
