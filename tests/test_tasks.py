"""The task table is the one place a thread's numbers live, and its metadata needs no build."""

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
from companion.tasks import VEHICLE_TASKS
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
        cls = row.thread_class()
        thread = cls("loop://") if issubclass(cls, SerialDevice) else cls()
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
    assert VEHICLE_TASKS["servo"].period_ms == 20.0 and VEHICLE_TASKS["servo"].max_catch_up == 3


def test_switching_off_a_device_or_the_estimator_removes_its_row() -> None:
    cfg = Config()
    cfg.devices.gps.enabled = False
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
    renamed = VEHICLE_TASKS["imu"].replace(name="imu2", thread_id=0)
    assert renamed.param_prefix == "IMU2" and renamed.budget_ms == 2.0


def test_bridge_rows_get_their_ids_from_the_manager() -> None:
    from companion.watchdog.manager import FIRST_ASSIGNED_ID
    from companion.watchdog.thread import ManagedThread

    mgr = ThreadManager(RuntimeContext(), [ManagedThread(VEHICLE_TASKS["control"])])
    a = ManagedThread(Task("alpha", restart=RestartType.TEMPORARY))
    b = ManagedThread(Task("beta"))
    mgr.add(a)
    mgr.add(b)
    assert (a.thread_id, b.thread_id) == (FIRST_ASSIGNED_ID, FIRST_ASSIGNED_ID + 1)
    assert a.restart is RestartType.TEMPORARY


def test_architecture_doc_lists_every_row_with_its_numbers() -> None:
    text = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    for row in VEHICLE_TASKS.values():
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
