"""The vehicle's table: every source and thread the aircraft runs, one row each, in start order.

Read it as ArduPilot's `scheduler_tasks[]` and python-can's interface table in one: what runs,
what paces it and within which budget, how the watchdog treats it, which slots it publishes,
what configuration it takes and what simulates it in SITL. Nothing else holds these facts:

* the runtime builds one thread per row (`Row.build`) and hands the thread its row, so no
  thread imports this table;
* the configuration's ``[devices.<name>]`` tables are keyed by the rows that take one, with the
  row's defaults (`device_defaults`), so a new device adds no field to `companion.core.config`;
* the bridges take thread ids and what each thread publishes from the rows they are handed
  (through the manager), never from a list of their own;
* `companion sim` builds a row's simulator (`Row.simulator`) for the SITL world;
* `companion drivers replay`, the flight report and `companion run --<device> PORT` take their
  device names from here.

A *source* is anything that publishes samples to the vehicle's slots: a serial device today
(`Row.device` set), a MAVLink connection tomorrow. A new one is one module (its thread class)
and one row. Ids 1..5 are the legacy protocol's contract (its data messages name the thesis
aircraft's sources by them; `tests/test_vehicle.py` checks the mapping); rows added later take
ids from 6 up, and a bridge's own threads get theirs from the manager.

The table imports no thread class: each row names its class as ``module:Class`` (loaded by
`companion.core.lazy.load`), so reading the table costs nothing and `companion --help` stays
fast.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

from companion.core.config import Config, ConfigError, DeviceConfig, load_config_given
from companion.watchdog.task import RestartType, Task
from companion.watchdog.thread import ManagedThread

__all__ = ["VEHICLE", "Row", "VehicleTable", "apply_device_ports", "device_settings",
           "fill_device_defaults", "load_vehicle_config"]


@dataclass(frozen=True)
class Row:
    """One source or thread of the vehicle: its supervision row plus what the runtime, the
    configuration and the simulator need to build and feed it."""

    task: Task
    summary: str
    """One line for people: what it is and what paces it (the driver replay tool, the docs)."""
    device: DeviceConfig | None = None
    """Defaults of its ``[devices.<name>]`` table (port, baud, enabled): a serial device.
    None: it takes no device configuration (the estimator, the control law)."""
    simulator: str = ""
    """``module:Class`` of the SITL simulator that feeds the device (see
    `companion.sim.plugins.DeviceSimulator`). Empty: the world simulates it itself (the thesis
    devices, whose timing is the world's) or nothing does."""
    replay: bool = True
    """A device whose raw bytes `companion drivers replay` plays through its driver (a
    `SerialDevice`); False for a source that is not one (the autopilot's MAVLink link)."""
    switch: str = ""
    """The `RuntimeOptions` flag that leaves this row out (``estimator``, ``control``); empty:
    the row runs whenever it is enabled."""
    config_table: str = ""
    """A top-level configuration table that is this device's ``[devices.<name>]`` by another
    name, with ``url`` for ``port`` (``[autopilot] url = "/dev/serial0,921600"``); empty: none."""

    @property
    def name(self) -> str:
        return self.task.name

    def build(self, settings: DeviceConfig | None = None) -> ManagedThread:
        """The row's thread, built by its class from the row and the device's settings."""
        cls = self.task.thread_class()
        thread = cls.from_row(self.task, settings or self.device if self.device else None)
        if not isinstance(thread, ManagedThread):
            raise TypeError(f"row {self.name}: {self.task.implementation} built a "
                            f"{type(thread).__name__}, not a ManagedThread")
        return thread


@dataclass(frozen=True)
class VehicleTable:
    """The rows in start order, looked up by name; immutable, so a test extends a copy."""

    rows: tuple[Row, ...]

    def __post_init__(self) -> None:
        names = [r.name for r in self.rows]
        ids = [r.task.thread_id for r in self.rows if r.task.thread_id]
        if len(set(names)) != len(names):
            raise ValueError(f"vehicle table: a name appears twice in {names}")
        if len(set(ids)) != len(ids):
            raise ValueError(f"vehicle table: a thread id appears twice in {ids}")

    def __iter__(self) -> Iterator[Row]:
        return iter(self.rows)

    def __len__(self) -> int:
        return len(self.rows)

    def __contains__(self, name: object) -> bool:
        return any(r.name == name for r in self.rows)

    def __getitem__(self, name: str) -> Row:
        for row in self.rows:
            if row.name == name:
                return row
        raise KeyError(f"no row {name!r} in the vehicle table (rows: {', '.join(self.names)})")

    @property
    def names(self) -> list[str]:
        return [r.name for r in self.rows]

    def devices(self) -> list[Row]:
        """The rows that are devices (take a ``[devices.<name>]`` table), in table order."""
        return [r for r in self.rows if r.device is not None]

    def device_defaults(self) -> dict[str, DeviceConfig]:
        """Each device's default settings, fresh copies (a configuration changes its own)."""
        return {r.name: dataclasses.replace(r.device) for r in self.rows if r.device is not None}

    def with_rows(self, rows: Iterable[Row]) -> VehicleTable:
        """This table with `rows` appended (a new source registered by a plug-in or a test);
        a row without an id takes the next free one above the table's."""
        out = list(self.rows)
        for row in rows:
            if not row.task.thread_id:
                next_id = max((r.task.thread_id for r in out), default=0) + 1
                row = dataclasses.replace(row, task=row.task.replace(thread_id=next_id))
            out.append(row)
        return VehicleTable(tuple(out))


def fill_device_defaults(cfg: Config, table: VehicleTable) -> Config:
    """Give `cfg` a ``[devices.<name>]`` for every device of `table` (its defaults where the
    configuration says nothing) and refuse a table the vehicle does not have, by name."""
    unknown = sorted(set(cfg.devices) - {r.name for r in table.devices()})
    if unknown:
        raise ConfigError(f"devices: unknown device {', '.join(map(repr, unknown))} "
                          f"(known: {', '.join(r.name for r in table.devices())})")
    for name, default in table.device_defaults().items():
        cfg.devices.setdefault(name, default)
    return cfg


def load_vehicle_config(path: Path | None, table: VehicleTable | None = None) -> Config:
    """The configuration file `path` (None: the defaults) over the devices of `table` (the
    thesis aircraft by default): every device present, an unknown one refused by name. A
    device the file switches on with a port switches off the devices whose slots it fills,
    unless the file configures them too (as ``--autopilot URL`` does, `apply_device_ports`)."""
    table = table or VEHICLE
    aliases = {r.config_table: r.name for r in table.devices() if r.config_table}
    cfg, given = load_config_given(path, table.device_defaults(), aliases)
    fill_device_defaults(cfg, table)
    _switch_off_filled(cfg, {name for name in given
                             if cfg.devices[name].enabled and cfg.devices[name].port}, given, table)
    return cfg


def device_settings(cfg: Config, name: str, table: VehicleTable | None = None) -> DeviceConfig:
    """The settings of device `name` in `cfg`, created from its row's defaults when the
    configuration has none yet (so a caller may change them in place)."""
    table = table or VEHICLE
    if name not in cfg.devices:
        row = table[name]
        if row.device is None:
            raise KeyError(f"{name!r} is not a device (devices: "
                           f"{', '.join(r.name for r in table.devices())})")
        cfg.devices[name] = dataclasses.replace(row.device)
    return cfg.devices[name]


def apply_device_ports(cfg: Config, ports: Mapping[str, str | None],
                       table: VehicleTable | None = None) -> None:
    """``companion run --<device> PORT``: each device given a port is switched on with it; a
    device whose slots another given device fills (the thesis IMU, GPS and servo board when
    ``--autopilot URL`` is given) is switched off unless its own port was given too, so an
    aircraft with a flight controller does not also look for the thesis's serial devices."""
    table = table or VEHICLE
    given = {name: port for name, port in ports.items() if port}
    for name, port in given.items():
        settings = device_settings(cfg, name, table)
        settings.port = port
        settings.enabled = True
    _switch_off_filled(cfg, set(given), set(given), table)


def _switch_off_filled(cfg: Config, sources: set[str], kept: set[str],
                       table: VehicleTable) -> None:
    """Switch off every device not in `kept` whose slots one of `sources` fills."""
    fills: set[str] = set()
    for name in sources:
        fills |= set(table[name].task.publishes)
    for row in table.devices():
        if row.name not in kept and fills & set(row.task.publishes):
            device_settings(cfg, row.name, table).enabled = False


def _device(port: str) -> DeviceConfig:
    return DeviceConfig(port=port, baud=115200, enabled=True)


VEHICLE = VehicleTable((
    Row(Task("imu", thread_id=1, paced_by="IMU frames (100 Hz)", budget_ms=2.0,
             watchdog_ms=500, message_ms=1000, restart=RestartType.TRANSIENT, escalate=True,
             implementation="companion.drivers.imu:ImuDriver", publishes=("imu", "imu_slow")),
        "20-byte binary frames at 100 Hz and a slow block once a second",
        device=_device("/dev/ttyS0")),
    Row(Task("gps", thread_id=2, paced_by="GPS epochs (10 Hz)", budget_ms=5.0,
             watchdog_ms=1000, message_ms=1000, restart=RestartType.TRANSIENT, escalate=True,
             implementation="companion.drivers.gps:GpsDriver", publishes=("gps",)),
        "NMEA 0183 and Ashtech $PASHR,POS sentences, 10 epochs a second",
        device=_device("/dev/ttyS1")),
    # A lost exchange is a lost command: catch up to three periods after a hiccup.
    Row(Task("servo", thread_id=3, period_ms=20.0, budget_ms=15.0, max_catch_up=3,
             watchdog_ms=500, message_ms=1000, restart=RestartType.TRANSIENT, escalate=True,
             implementation="companion.drivers.servo:ServoDriver", publishes=("servo",)),
        "command and pilot frames exchanged every 20 ms",
        device=_device("/dev/ttyS2")),
    Row(Task("estimator", thread_id=4, paced_by="IMU samples (imu_stream)", budget_ms=3.0,
             watchdog_ms=1000, message_ms=1000, param_prefix="EST",
             restart=RestartType.TRANSIENT, escalate=True,
             implementation="companion.estimation.thread:EstimatorThread",
             publishes=("estimator",)),
        "the GPS/INS filter, one cycle per IMU sample", switch="estimator"),
    Row(Task("control", thread_id=5, paced_by="estimates (state.estimator)", budget_ms=2.0,
             watchdog_ms=1000, message_ms=1000, param_prefix="CTL",
             restart=RestartType.TRANSIENT, escalate=True,
             implementation="companion.control:ControlThread", publishes=("control",)),
        "the control law, one step per estimate", switch="control"),
    # Beside a flight controller: a MAVLink link (serial TELEM cable, TCP or UDP) that fills the
    # same slots as the thesis devices. Off until a URL is given (--autopilot URL).
    Row(Task("autopilot", thread_id=6, paced_by="the autopilot's messages", budget_ms=5.0,
             watchdog_ms=2000, message_ms=1000, param_prefix="AP",
             restart=RestartType.TRANSIENT,
             implementation="gcs_bridge.autopilot.link:AutopilotLink",
             publishes=("imu", "imu_slow", "gps", "servo", "autopilot", "truth", "gps2",
                        "battery")),
        "MAVLink link to a flight controller (ArduPilot, PX4): its IMU, GPS, RC, outputs and "
        "own estimate", device=DeviceConfig(port="", baud=921600, enabled=False), replay=False,
        config_table="autopilot"),
))
"""The thesis aircraft (IMU, GPS and servo board on serial ports, the estimator, the control
law) and, switched on by a URL, the link to a flight controller beside which it flies."""
