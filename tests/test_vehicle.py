"""The vehicle's table is the one place a source's or thread's facts live: its numbers, its
configuration, its ids on the wire and its simulator; a new device is one module and one row."""

from __future__ import annotations

import os
import re
import threading
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_for

from companion.core.config import Config
from companion.core.state import GpsFix
from companion.drivers.serial_device import SerialDevice
from companion.logs.layout import RecordLayout
from companion.runtime import Runtime, RuntimeOptions, declared_registry, vehicle_tasks
from companion.vehicle import VEHICLE, Row, VehicleTable, device_settings
from companion.watchdog import RuntimeContext, Task, ThreadManager
from companion.watchdog.task import RestartType

ROOT = Path(__file__).resolve().parents[1]


def _spec_table(specs: Iterable[Any]) -> dict[str, tuple[Any, ...]]:
    return {s.name: (s.ptype, s.default, s.min, s.max, s.unit, s.description,
                     s.read_only, s.reboot_required) for s in specs}


def test_parameter_metadata_is_read_without_building_and_matches_a_built_runtime(
        tmp_path: Path) -> None:
    cfg = Config()
    cfg.logs.dir = str(tmp_path)
    static = declared_registry(cfg)
    built = Runtime(cfg, RuntimeOptions(dry=True))
    try:
        by_build = _spec_table(built.ctx.params.specs())
    finally:
        built.shutdown()
    by_table = _spec_table(static.specs())
    assert by_table == by_build
    assert len(by_table) > 60
    assert static.get("SYS_VEHICLE_ID") == cfg.vehicle.id


def test_every_thread_is_built_from_its_row() -> None:
    cfg = Config()
    rows = vehicle_tasks(cfg, RuntimeOptions())
    assert [r.name for r in rows] == ["imu", "gps", "servo", "estimator", "control"]
    assert [r.thread_id for r in rows] == [1, 2, 3, 4, 5]
    for row in rows:
        thread = VEHICLE[row.name].build(Config().devices.get(row.name))
        if isinstance(thread, SerialDevice):
            assert thread.url == VEHICLE[row.name].device.port  # type: ignore[union-attr]
        assert thread.task is row
        assert (thread.name, thread.thread_id, thread.period_ms, thread.budget_ms,
                thread.param_prefix, thread.restart, thread.max_catch_up,
                thread.shutdown_timeout_ms) == (
            row.name, row.thread_id, row.period_ms, row.effective_budget_ms, row.param_prefix,
            row.restart, row.max_catch_up, row.shutdown_timeout_ms)
        names = {s.name for s in thread.param_specs()}
        assert {f"{row.param_prefix}_WDG_MS", f"{row.param_prefix}_ENABLE"} <= names
        wdg = next(s for s in thread.param_specs() if s.name.endswith("_WDG_MS"))
        assert wdg.default == row.watchdog_ms
    assert VEHICLE["servo"].task.period_ms == 20.0 and VEHICLE["servo"].task.max_catch_up == 3


def test_switching_off_a_device_or_the_estimator_removes_its_row() -> None:
    cfg = Config()
    device_settings(cfg, "gps").enabled = False
    names = [r.name for r in vehicle_tasks(cfg, RuntimeOptions(estimator=False))]
    assert names == ["imu", "servo", "control"]


def test_a_row_that_names_a_missing_class_is_an_error_naming_it() -> None:
    row = Task("ghost", implementation="companion.nothing_here:Ghost")
    with pytest.raises(LookupError, match=r"ghost.*companion\.nothing_here:Ghost"):
        row.param_specs()


def test_a_row_checks_itself_and_derives_its_prefix() -> None:
    assert Task("legacy-rx").param_prefix == "LEGACY"
    assert Task("estimator", param_prefix="est").param_prefix == "EST"
    assert Task("a", period_ms=10.0).effective_budget_ms == 10.0
    assert Task("a").effective_budget_ms == 10.0
    with pytest.raises(ValueError, match="period_ms"):
        Task("a", period_ms=0.0)
    renamed = VEHICLE["imu"].task.replace(name="imu2", thread_id=0)
    assert renamed.param_prefix == "IMU2" and renamed.budget_ms == 2.0


def test_bridge_rows_get_their_ids_from_the_manager() -> None:
    from companion.watchdog.manager import FIRST_ASSIGNED_ID
    from companion.watchdog.thread import ManagedThread

    mgr = ThreadManager(RuntimeContext(), [ManagedThread(VEHICLE["control"].task)])
    a = ManagedThread(Task("alpha", restart=RestartType.TEMPORARY))
    b = ManagedThread(Task("beta"))
    mgr.add(a)
    mgr.add(b)
    assert (a.thread_id, b.thread_id) == (FIRST_ASSIGNED_ID, FIRST_ASSIGNED_ID + 1)
    assert a.restart is RestartType.TEMPORARY


def test_architecture_doc_lists_every_row_with_its_numbers() -> None:
    text = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    for row in (r.task for r in VEHICLE):
        line = next((ln for ln in text.splitlines() if ln.startswith(f"| {row.name} |")), None)
        assert line is not None, f"docs/architecture.md: no task-table row for {row.name}"
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert cells[1] == str(row.thread_id), line
        assert cells[5] == str(row.watchdog_ms), line
        assert cells[7] == row.param_prefix, line


# ------------------------------------------------------------------ the serial base's read path
class _LineDevice(SerialDevice):
    """A device a new user might add: newline-terminated readings, raw bytes logged."""

    raw_format = 2

    def __init__(self, url: str) -> None:
        super().__init__(Task("lines", paced_by="lines"), url=url, read_timeout_s=0.05)
        self._buf = b""
        self.published: list[bytes] = []

    def decode(self, data: bytes | None, t_ns: int) -> Iterable[object]:
        if not data:
            return []
        self._buf += data
        *lines, self._buf = self._buf.split(b"\n")
        return lines

    def publish(self, item: object, t_ns: int) -> int:
        assert isinstance(item, bytes)
        self.published.append(item)
        return 1


def test_a_driver_that_supplies_decode_and_publish_gets_the_whole_read_path(
        tmp_path: Path) -> None:
    from companion.logs import LogService
    from companion.logs.reader import read_log

    master, slave = os.openpty()
    try:
        logs = LogService(tmp_path)
        logs.start()
        ctx = RuntimeContext(logs=logs)
        dev = _LineDevice(os.ttyname(slave))
        assert "LINES_LOG_RAW" in {s.name for s in dev.param_specs()}
        mgr = ThreadManager(ctx, [dev])
        runner = threading.Thread(target=mgr.run, daemon=True)
        runner.start()
        try:
            assert wait_for(lambda: dev.in_periodic, 5.0)
            for k in range(5):
                os.write(master, b"reading %d\n" % k)
            assert wait_for(lambda: len(dev.published) == 5, 5.0)
            assert wait_for(lambda: dev.cycles == 5, 5.0)
        finally:
            mgr.request_stop()
            runner.join(5.0)
            mgr.shutdown()
            logs.close()
        assert dev.published == [b"reading %d" % k for k in range(5)]
        raw = b"".join(a.tobytes() for s in read_log(tmp_path / "lines.bin").streams_of(2)
                       for a in s.arrays())
        assert raw == b"".join(b"reading %d\n" % k for k in range(5))
    finally:
        os.close(master)
        os.close(slave)


def test_the_gps_log_format_is_the_fix_record_itself() -> None:
    layout = RecordLayout.of(GpsFix)
    # the layout gps.bin has always had, derived now, not hand-listed; a dual-antenna
    # receiver's heading came last, so older readers' columns keep their places
    assert layout.fmt == ("%.3f,%.9lf,%.9lf,%.3f,%hhu,%hhu,%.2f,%.2f,%.2f,%.2f,%.3f,%.2f,"
                          "%.3f,%.3f,%.3f,%.3f,%.3f,%.2f,%.2f")
    assert list(layout.names[-2:]) == ["latency_ms", "heading_deg"] and len(layout.names) == 19
    values = layout.values(GpsFix(0, 1.5, 43.0, 10.0, None, 1, None, latency_s=0.05))
    assert values[:3] == (1.5, 43.0, 10.0) and values[3] != values[3]  # NaN for a missing float
    assert values[4:6] == (1, 0) and values[-2] == pytest.approx(50.0)
    assert values[-1] != values[-1]  # no heading: NaN
    assert re.fullmatch(r"[a-z_]+", "_".join(layout.names))


def test_a_start_refused_by_a_bad_key_file_leaves_no_empty_flight_directory(
        tmp_path: Path) -> None:
    from gcs_bridge.signing import KeyFileError

    key = tmp_path / "mavlink.key"
    key.write_text("ab" * 32 + "\n")
    os.chmod(key, 0o644)  # readable by others: refused
    cfg = Config()
    cfg.logs.dir = str(tmp_path / "flights")
    cfg.mavlink.key_file = str(key)
    cfg.legacy.enabled = False
    with pytest.raises(KeyFileError, match="chmod 600"):
        Runtime(cfg, RuntimeOptions())
    assert not any((tmp_path / "flights").iterdir())


# ------------------------------------------------------------------ the table's own facts
def test_the_legacy_wire_ids_are_the_tables_ids() -> None:
    """The legacy protocol's contract names the thesis aircraft's sources 1..5; the table is
    where those ids live, and the codec's enum is the contract's copy of them."""
    from legacy_protocol.messages import ThreadId

    assert {t.name.lower(): int(t) for t in ThreadId} == {
        row.name: row.task.thread_id for row in VEHICLE if row.task.thread_id <= 5}


def test_every_published_slot_is_a_slot_of_the_vehicle_state() -> None:
    from companion.core.state import VehicleState
    from companion.core.sync import DataSlot

    state = VehicleState()
    for row in VEHICLE:
        assert row.task.publishes, f"{row.name} publishes nothing"
        for name in row.task.publishes:  # a field of the state, or a named slot
            assert isinstance(state.slot(name), DataSlot), (row.name, name)
    assert set(state.named) == {"autopilot", "truth", "gps2", "battery"}  # the autopilot link's
    # a kind of data the state has no field for gets a named slot, the same one every time
    assert state.slot("airspeed") is state.slot("airspeed") and "airspeed" in state.named
    assert state.slot("gps") is state.gps


def test_a_table_refuses_a_name_or_id_twice_and_a_new_row_takes_the_next_id() -> None:
    imu = VEHICLE["imu"]
    with pytest.raises(ValueError, match="name appears twice"):
        VehicleTable((imu, imu))
    with pytest.raises(ValueError, match="thread id appears twice"):
        VehicleTable((imu, Row(imu.task.replace(name="imu2"), "a second IMU")))
    extended = VEHICLE.with_rows([Row(Task("baro"), "a barometer")])
    assert extended["baro"].task.thread_id == 7 and len(VEHICLE) == 6
    with pytest.raises(KeyError, match="no row 'pitot'.*imu, gps, servo, estimator, control, "
                                       "autopilot"):
        VEHICLE["pitot"]


def _fly_lockstep(tmp: Path, vehicle: VehicleTable) -> tuple[dict[str, Any], Path]:
    from companion.sim.lockstep import run_lockstep
    from companion.sim.runner import SimOptions

    cfg = Config()
    cfg.logs.dir = str(tmp / "flights")
    cfg.params.file = str(tmp / "params.parm")
    sim = SimOptions(scenario="turns", seed=11, imu_profile="simple", gps_profile="simple",
                     turbulence="none")
    summary = run_lockstep(cfg, sim, 20.0, handle_signals=False, vehicle=vehicle)
    return summary, Path(summary["flight_dir"])


def test_a_device_added_as_one_module_and_one_row_flies_in_lockstep(tmp_path: Path) -> None:
    """`tests/plugin_airspeed.py` holds a whole new device (wire format, driver, simulator) and
    its row; the table extended with that row flies it: its thread runs at its rate, its log
    is written, its slot carries the true airspeed, and no other sensor's bytes change."""
    import numpy as np
    from plugin_airspeed import NOISE_M_S, ROW

    from companion.logs.reader import read_log

    summary, fdir = _fly_lockstep(tmp_path / "with", VEHICLE.with_rows([ROW]))
    threads = {t["name"]: t for t in summary["threads"]}
    assert set(threads) == {"imu", "gps", "servo", "estimator", "control", "airspeed"}
    aspd = threads["airspeed"]
    assert aspd["restarts"] == 0 and aspd["stalls"] == 0, aspd
    assert aspd["rate_hz"] == pytest.approx(10.0, rel=0.02), aspd
    assert aspd["counters"]["bad_lines"] == 0, aspd
    run = __import__("json").loads((fdir / "run.json").read_text())
    assert run["config"]["devices"]["airspeed"]["port"].startswith("lockstep://")
    assert {"name": "airspeed", "id": 7} in run["threads"]  # the next id above the table's
    measured = read_log(fdir / "airspeed.bin").data(1)
    truth = read_log(fdir / "truth.bin").data(1)
    assert len(measured["time_s"]) >= 190  # 10 Hz for 20 s
    true_at = np.interp(measured["time_s"], truth["time_s"], truth["airspeed_m_s"])
    err = measured["airspeed_m_s"] - true_at
    assert float(np.std(err)) < 3 * NOISE_M_S and abs(float(np.mean(err))) < NOISE_M_S
    assert float(np.mean(true_at)) > 20.0  # it flew
    # the same flight without the device: every record the flights share is the same, bit for
    # bit, times included (the device's generator is drawn after every other sensor's); the
    # flight with one more thread to start ends a few ticks later on the simulated clock
    _, plain = _fly_lockstep(tmp_path / "without", VEHICLE)
    assert not (plain / "airspeed.bin").exists()
    for name in ("truth.bin", "imu.bin", "gps.bin", "servo.bin", "estimator.bin", "control.bin"):
        ours, theirs = read_log(fdir / name).data(1), read_log(plain / name).data(1)
        n = min(len(ours), len(theirs))
        assert n > 0.98 * max(len(ours), len(theirs)), (name, len(ours), len(theirs))
        assert ours[:n].tobytes() == theirs[:n].tobytes(), name


def test_a_configuration_file_beside_an_autopilot_is_what_the_command_line_is(
        tmp_path: Path) -> None:
    """``[autopilot] url = ...`` (or ``[devices.autopilot] port = ...``) switches the link on
    and the thesis devices whose slots it fills off, as ``--autopilot URL`` does; a thesis
    device the file configures itself stays on; two spellings of one device are refused."""
    from companion.core.config import ConfigError
    from companion.vehicle import load_vehicle_config

    def load(text: str) -> Config:
        path = tmp_path / "companion.toml"
        path.write_text(text, encoding="utf-8")
        return load_vehicle_config(path)

    for text in ('[autopilot]\nurl = "/dev/serial0,921600"\n',
                 '[devices.autopilot]\nport = "/dev/serial0,921600"\nenabled = true\n'):
        cfg = load(text)
        link = cfg.devices["autopilot"]
        assert (link.port, link.enabled) == ("/dev/serial0,921600", True), text
        assert not any(cfg.devices[n].enabled for n in ("imu", "gps", "servo")), text
    cfg = load('[autopilot]\nurl = "tcp:127.0.0.1:5760"\n[devices.gps]\nport = "/dev/ttyUSB0"\n')
    assert cfg.devices["gps"].enabled and not cfg.devices["imu"].enabled
    assert cfg.devices["autopilot"].port == "tcp:127.0.0.1:5760"
    cfg = load("")  # without an autopilot, the thesis aircraft as before
    assert all(cfg.devices[n].enabled for n in ("imu", "gps", "servo"))
    assert not cfg.devices["autopilot"].enabled
    with pytest.raises(ConfigError, match=r"\[autopilot\] and \[devices.autopilot\]"):
        load('[autopilot]\nurl = "a"\n[devices.autopilot]\nport = "b"\n')
    with pytest.raises(ConfigError, match="'url' and 'port'"):
        load('[autopilot]\nurl = "a"\nport = "b"\n')
    with pytest.raises(ConfigError, match="unknown setting 'devices.autopilot.speed'"):
        load('[autopilot]\nurl = "a"\nspeed = 3\n')
