"""MAVSDK 4.1 (the native Python binding) against the bridge's services, over UDP.

LogFiles (LOG_* download of a flight archive), Ftp (the read-only MAVLink FTP server over the
flight root), ComponentMetadata (parameter metadata over mftp://), Shell (the SERIAL_CONTROL
console) and Telemetry (default stream rates), each against a `SyntheticVehicle` whose flight
root holds an older finished flight next to the current one.
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from conftest import free_udp_port, quiet_mavsdk, wait_for
from mavsdk.plugins.component_metadata.component_metadata import ComponentMetadata, MetadataType
from mavsdk.plugins.ftp.ftp import FilesystemEntry, Ftp, FtpError, FtpResult
from mavsdk.plugins.log_files.log_files import LogFiles, LogFilesResult
from mavsdk.plugins.shell.shell import Device, Shell
from mavsdk.plugins.telemetry.telemetry import Telemetry
from support.synthetic_vehicle import SyntheticVehicle

# the MAVSDK connection helper is shared with the synthetic-vehicle MAVSDK tests
from test_gcs_mavsdk import mavsdk_on

from companion.logs.archive import FlightArchive
from companion.logs.cli import main as logs_main
from companion.logs.writer import LogService
from gcs_bridge.bridge_params import BRIDGE_PARAMS
from gcs_bridge.services.console import PROMPT

OLD = "20261123T100000Z"
CURRENT = "20261124T120000Z"
RANDOM_BYTES = 200_003  # not a multiple of 90 (LOG_DATA) nor of 239 (FTP data)


@pytest.fixture(scope="module", autouse=True)
def _mavsdk_quiet() -> Iterator[None]:
    with quiet_mavsdk():
        yield


@dataclass
class Flights:
    root: Path
    old: Path
    current: Path
    random_file: Path
    log_file: Path


def _write_log(flight_dir: Path, name: str, records: int) -> Path:
    t = [1_700_000_000 * 10**9]

    def clock() -> int:
        t[0] += 1_000_000
        return t[0]

    with LogService(flight_dir, flush_period_ms=10, clock_ns=clock) as svc:
        lg = svc.open(name)
        lg.define(1, "%d,%f,%lf", ["n", "x", "y"])
        lg.begin()
        for k in range(records):
            assert lg.log(1, k, k / 4, k / 3)
        lg.end()
    return flight_dir / f"{name}.bin"


@pytest.fixture
def flights(tmp_path: Path) -> Flights:
    root = tmp_path / "flights"
    old, current = root / OLD, root / CURRENT
    log_file = _write_log(old, "imu", 2000)
    random_file = old / "random.dat"
    random_file.write_bytes(os.urandom(RANDOM_BYTES))
    _write_log(current, "imu", 10)  # the flight being recorded (a log server lists it too)
    return Flights(root, old, current, random_file, log_file)


@contextmanager
def vehicle_and_mavsdk(flights: Flights) -> Iterator[tuple[SyntheticVehicle, Any]]:
    port = free_udp_port()
    with SyntheticVehicle([f"udpout:127.0.0.1:{port}"], flight_dir=flights.current) as v, \
            mavsdk_on(port) as system:
        yield v, system


class Outcome:
    """The final result of an asynchronous MAVSDK call (progress results skipped)."""

    def __init__(self, progress: Any) -> None:
        self.progress = progress
        self.done = threading.Event()
        self.result: Any = None
        self.last: Any = None

    def __call__(self, result: Any, data: Any, _user: Any) -> None:
        self.last = data
        if result != self.progress:
            self.result = result
            self.done.set()

    def wait(self, timeout_s: float) -> Any:
        assert self.done.wait(timeout_s), f"no final result within {timeout_s} s (last {self.last})"
        return self.result


def test_log_files_list_download_and_info(flights: Flights, tmp_path: Path) -> None:
    with vehicle_and_mavsdk(flights) as (_v, system):
        log_files = LogFiles(system)
        entries = log_files.get_entries()
        assert len(entries) == 2, [str(e) for e in entries]
        old_entry, current_entry = sorted(entries, key=lambda e: e.id)
        old_archive = FlightArchive.snapshot(flights.old)
        assert old_entry.size_bytes == old_archive.size
        assert old_archive.size > RANDOM_BYTES
        assert current_entry.size_bytes == FlightArchive.snapshot(flights.current).size
        target = tmp_path / "download" / "old_flight.bin"
        target.parent.mkdir()
        outcome = Outcome(LogFilesResult.NEXT)
        log_files.download_log_file_async(old_entry, str(target), outcome)
        assert outcome.wait(30.0) == LogFilesResult.SUCCESS
    assert target.read_bytes() == old_archive.read(0, old_archive.size)
    # `companion logs info` unpacks the downloaded archive and reads the flight's log
    assert logs_main(["info", str(target)]) == 0


def test_ftp_list_download_and_refusals(flights: Flights, tmp_path: Path) -> None:
    local = tmp_path / "ftp_down"
    local.mkdir()
    with vehicle_and_mavsdk(flights) as (_v, system):
        ftp = Ftp(system)
        listing = ftp.list_directory("/")
        dirs = {e.name for e in listing.entries
                if e.entry_type == FilesystemEntry.EntryType.DIRECTORY}
        assert {OLD, CURRENT} <= dirs, [str(e) for e in listing.entries]
        inside = {e.name: e for e in ftp.list_directory(f"/{OLD}").entries}
        assert inside["random.dat"].size_bytes == RANDOM_BYTES
        assert inside["imu.bin"].size_bytes == flights.log_file.stat().st_size

        for name, burst in (("random.dat", True), ("imu.bin", False)):
            outcome = Outcome(FtpResult.NEXT)
            ftp.download_async(f"/{OLD}/{name}", str(local), burst, outcome)
            assert outcome.wait(30.0) == FtpResult.SUCCESS, name
            assert (local / name).read_bytes() == (flights.old / name).read_bytes(), name

        outcome = Outcome(FtpResult.NEXT)
        ftp.download_async(f"/{OLD}/missing.dat", str(local), False, outcome)
        assert outcome.wait(10.0) == FtpResult.FILE_DOES_NOT_EXIST
        # MAVSDK creates the local file before it opens the remote one: it stays empty
        assert (local / "missing.dat").stat().st_size == 0

        # CalcFileCRC32 (MAVLink's CRC32, not zlib's) agrees with the local copy
        assert ftp.are_files_identical(str(flights.random_file), f"/{OLD}/random.dat")
        different = tmp_path / "different.dat"
        different.write_bytes(flights.random_file.read_bytes()[:-1] + b"\0")
        assert not ftp.are_files_identical(str(different), f"/{OLD}/random.dat")

        # read-only without a signing key: every change is refused with FILE_PROTECTED
        upload = tmp_path / "upload.txt"
        upload.write_bytes(b"not welcome\n")
        outcome = Outcome(FtpResult.NEXT)
        ftp.upload_async(str(upload), f"/{OLD}", outcome)
        assert outcome.wait(10.0) == FtpResult.FILE_PROTECTED
        for method, args in (("remove_file", (f"/{OLD}/random.dat",)),
                             ("create_directory", (f"/{OLD}/new_dir",)),
                             ("remove_directory", (f"/{CURRENT}",)),
                             ("rename", (f"/{OLD}/random.dat", f"/{OLD}/renamed.dat"))):
            with pytest.raises(FtpError) as info:
                getattr(ftp, method)(*args)
            assert info.value.result == FtpResult.FILE_PROTECTED, method
    assert not (flights.old / "upload.txt").exists()
    assert (flights.old / "random.dat").stat().st_size == RANDOM_BYTES
    assert not (flights.old / "new_dir").exists() and flights.current.is_dir()
    assert sorted(p.name for p in flights.old.iterdir()) == ["imu.bin", "random.dat"]


def test_component_metadata_parameters(flights: Flights) -> None:
    with vehicle_and_mavsdk(flights) as (v, system):
        spec = v.params.spec("MAV_ATT_HZ")
        metadata = ComponentMetadata(system)
        done = threading.Event()
        got: list[Any] = []

        def on_metadata(update: Any, _user: Any) -> None:
            got.append(update)
            if update.type in (MetadataType.PARAMETER, MetadataType.ALL_COMPLETED):
                done.set()

        metadata.subscribe_metadata_available(on_metadata)
        metadata.request_autopilot_component()
        assert done.wait(15.0), [str(u) for u in got]
        params_json = metadata.get_metadata(1, MetadataType.PARAMETER).json_metadata
        document = json.loads(params_json)
        by_name = {p["name"]: p for p in document["parameters"]}
        assert len(by_name) == len(v.params)
        att = by_name["MAV_ATT_HZ"]
        assert att["units"] == spec.unit == "Hz"
        assert att["shortDesc"] and spec.description.startswith(att["shortDesc"])
        assert att["default"] == spec.default and att["type"] == "Float"


def test_shell_threads(flights: Flights) -> None:
    with vehicle_and_mavsdk(flights) as (_v, system):
        shell = Shell(system)
        lock = threading.Lock()
        text: list[str] = []

        def on_receive(received: Any, _user: Any) -> None:
            with lock:
                text.append(received.data)

        def output() -> str:
            with lock:
                return "".join(text)

        def complete() -> bool:
            out = output()
            return (all(name in out for name in ("imu", "gps", "servo", "estimator"))
                    and out.endswith(PROMPT))

        shell.subscribe_receive(on_receive)
        # MAVSDK sets RESPOND only when it has a receive callback, but subscribe_receive just
        # posts the insertion to its io thread: a send right after it may go out without
        # RESPOND, which the console (like PX4's nsh) executes without answering. So the line
        # is sent again, a bounded number of times, until an answer comes.
        for _ in range(5):
            shell.send("threads\n", Device.SHELL)
            if wait_for(lambda: bool(output()), 1.0):
                break
        assert wait_for(complete, 5.0), repr(output())
        assert f"{PROMPT}threads\n" in output()  # the console echoes the line after its prompt


def test_attitude_default_rate(flights: Flights) -> None:
    with vehicle_and_mavsdk(flights) as (_v, system):
        telemetry = Telemetry(system)
        lock = threading.Lock()
        stamps: list[float] = []

        def on_attitude(_value: Any, *_: Any) -> None:
            with lock:
                stamps.append(time.monotonic())

        telemetry.subscribe_attitude_euler(on_attitude)
        assert wait_for(lambda: len(stamps) >= 3, 5.0)  # the stream is flowing: start counting
        with lock:
            start = stamps[-1]

        def window() -> list[float]:
            with lock:
                return [t for t in stamps if t >= start]

        assert wait_for(lambda: window()[-1] - start >= 2.0, 5.0)
        w = window()
        rate_hz = (len(w) - 1) / (w[-1] - w[0])
        # MAV_ATT_HZ defaults to 20 Hz. The rate is taken on arrival, in MAVSDK's callback
        # thread, over 2 s or more: a busy core delays single messages without losing them, so
        # it holds within 15 % (a stream at half or double its rate fails)
        default_hz = float(next(p.default for p in BRIDGE_PARAMS if p.name == "MAV_ATT_HZ"))
        assert abs(rate_hz - default_hz) <= 0.15 * default_hz, \
            f"{rate_hz:.1f} Hz over {w[-1] - w[0]:.2f} s, MAV_ATT_HZ {default_hz:g}"
