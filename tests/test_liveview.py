"""Rerun live view and replay: .rrd files read back with rerun's own Python API."""

from __future__ import annotations

import select
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rerun as rr
from conftest import free_tcp_port

from companion.cli import main as companion_main
from companion.core.config import Config, ConfigError
from companion.core.state import EstimatorState, GpsFix, ImuSample, ServoState
from companion.liveview import LiveView, LiveViewThread, ViewerError, open_recording, replay_flight
from companion.liveview import entities as E
from companion.liveview.tail import LogTail
from companion.report import load_flight
from companion.watchdog import RuntimeContext, ThreadManager

FLIGHT_S = 20.0


@dataclass
class LiveRun:
    flight_dir: Path
    rrd: Path
    summary: dict[str, Any]
    view: LiveView
    host_s: float


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> LiveRun:
    """A 20 s SITL flight at 5x with the live view writing an .rrd, as `--rerun-save` does."""
    from companion.sim.runner import FAST_SCALE, SimOptions, run_sim

    work = tmp_path_factory.mktemp("live")
    rrd = work / "live.rrd"
    cfg = Config()
    cfg.logs.dir = str(work / "flights")
    cfg.params.file = str(work / "p.parm")
    cfg.mavlink.endpoints = []
    cfg.legacy.enabled = False
    views: list[LiveView] = []

    def attach(rt: Any) -> None:  # what Runtime does for cfg.rerun.save
        view = LiveView(rt.ctx, rt.manager, save_path=rrd)
        rt.bridges.append(view)
        views.append(view)

    t0 = time.monotonic()
    summary = run_sim(cfg, SimOptions(scale=FAST_SCALE), FLIGHT_S, handle_signals=False,
                      on_runtime=attach)
    return LiveRun(Path(summary["flight_dir"]), rrd, summary, views[0], time.monotonic() - t0)


def rows_per_entity(path: Path) -> dict[str, int]:
    rows: dict[str, int] = {}
    for chunk in rr.chunk.RrdReader(path).stream():
        if not chunk.is_static:
            rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    return rows


def timeline_ns(path: Path, entity: str) -> np.ndarray:
    out = []
    for chunk in rr.chunk.RrdReader(path).stream():
        if chunk.entity_path == entity and not chunk.is_static:
            col = chunk.to_record_batch().column(E.TIMELINE)
            out.append(np.asarray(col.cast("int64")))
    return np.concatenate(out) if out else np.zeros(0, dtype=np.int64)


def column(path: Path, entity: str, component: str) -> list[Any]:
    out: list[Any] = []
    for chunk in rr.chunk.RrdReader(path).stream():
        batch = chunk.to_record_batch()
        if chunk.entity_path == entity and component in batch.schema.names:
            out += batch.column(component).to_pylist()
    return out


def test_live_rrd_holds_the_expected_entities(live: LiveRun) -> None:
    rows = rows_per_entity(live.rrd)
    expected = {
        "/" + p for p in (E.IMU_RATES, E.IMU_FORCE, E.GPS_SATS, E.GPS_HDOP, E.GPS_FIX, E.AIRCRAFT,
                          E.TRUTH_AIRCRAFT, E.ATTITUDE_ESTIMATE, E.ATTITUDE_TRUTH, E.SERVO_PILOT,
                          E.SERVO_COMMAND, E.SERVO_BATTERY, E.GPS_PATH, E.ESTIMATE_PATH,
                          E.TRUTH_PATH, E.thread_path("imu", "rate_hz"), E.THREAD_EVENTS)
    }
    assert expected <= set(rows), sorted(expected - set(rows))
    # At most one IMU sample per tick (25 Hz of host time), none twice.
    ticks = live.view.thread.cycles
    assert 10 <= rows["/" + E.IMU_RATES] <= ticks, (rows["/" + E.IMU_RATES], ticks)
    # Truth is followed from the growing truth.bin, every 4th record, until the view stops.
    truth = load_flight(live.flight_dir).block("truth", 1)
    assert truth is not None
    polls = ticks // 10 + 2
    assert 0.6 * truth.size / 4 <= rows["/" + E.ATTITUDE_TRUTH] <= truth.size / 4 + polls
    assert rows == {("/" + k): v for k, v in live.view.samples.items() if ("/" + k) in rows}
    rates = column(live.rrd, "/" + E.IMU_RATES, "Scalars:scalars")
    assert all(len(r) == 3 for r in rates)
    assert np.abs(np.asarray(rates)).max() < 400.0  # deg/s, a docile aircraft


def test_live_timeline_is_the_runtime_clock(live: LiveRun) -> None:
    imu = load_flight(live.flight_dir).block("imu", 1)
    assert imu is not None
    t = timeline_ns(live.rrd, "/" + E.IMU_RATES)
    assert t.size and np.all(np.diff(t) > 0)
    lo, hi = imu["time_s"][0] * 1e9, imu["time_s"][-1] * 1e9
    assert lo - 0.5e9 <= t.min() and t.max() <= hi + 0.5e9


def test_live_view_never_disturbs_the_flight_threads(live: LiveRun) -> None:
    threads = {t["name"]: t for t in live.summary["threads"]}
    view = live.view.thread
    assert "liveview" in threads and threads["liveview"]["restarts"] == 0
    assert view.cycles > 20
    assert threads["imu"]["restarts"] == 0 and threads["imu"]["stalls"] == 0
    assert threads["imu"]["rate_hz"] == pytest.approx(100.0, rel=0.05)
    assert threads["gps"]["rate_hz"] == pytest.approx(10.0, rel=0.1)
    # The view's own Python work is a small share of one core (the benchmark measures it fully).
    assert view.logging_ns / 1e9 / live.host_s < 0.15


def test_replay_puts_every_record_on_the_log_timestamps(live: LiveRun, tmp_path: Path) -> None:
    out = tmp_path / "replay.rrd"
    result = replay_flight(live.flight_dir, out)
    assert not result.missing, result.missing
    rows = rows_per_entity(out)
    fd = load_flight(live.flight_dir)
    for name, entity in (("imu", E.IMU_RATES), ("gps", E.GPS_SATS), ("servo", E.SERVO_PILOT),
                         ("estimator", E.ATTITUDE_ESTIMATE), ("truth", E.ATTITUDE_TRUTH)):
        data = fd.block(name, 1)
        assert data is not None
        assert rows["/" + entity] == data.size, name
    imu = fd.block("imu", 1)
    assert imu is not None
    t = timeline_ns(out, "/" + E.IMU_RATES)
    assert np.allclose(np.sort(t) / 1e9, imu["time_s"], atol=1e-6)
    events = [row[0] for row in column(out, "/" + E.THREAD_EVENTS, "TextLog:text")]
    assert "imu: started" in events and "imu: stopped" in events


def test_view_cli_and_a_partial_flight(live: LiveRun, tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    d = tmp_path / "partial"
    d.mkdir()
    (d / "imu.bin").write_bytes((live.flight_dir / "imu.bin").read_bytes())
    out = tmp_path / "view.rrd"
    assert companion_main(["logs", "view", str(d), "--rerun-save", str(out)]) == 0
    captured = capsys.readouterr()
    assert "replayed" in captured.out and "gps.bin is missing" in captured.err
    rows = rows_per_entity(out)
    imu = load_flight(d).block("imu", 1)
    assert imu is not None and rows["/" + E.IMU_RATES] == imu.size > 100
    assert "/" + E.GPS_SATS not in rows
    assert companion_main(["logs", "view", str(tmp_path / "nowhere"), "--rerun-save", str(out)]) == 1
    assert companion_main(["logs", "view", str(d), "--rerun-save", str(tmp_path / "no" / "x.rrd")]) == 1
    assert "does not exist" in capsys.readouterr().err


def test_bad_destinations_are_refused_by_name(tmp_path: Path) -> None:
    with pytest.raises(ViewerError, match="no rerun destination"):
        open_recording()
    with pytest.raises(ViewerError, match="missing-dir"):
        open_recording(save_path=tmp_path / "missing-dir" / "x.rrd")
    ctx = RuntimeContext()
    manager = ThreadManager(ctx, [])
    with pytest.raises(ConfigError, match="rerun.save .*missing-dir"):
        LiveView(ctx, manager, save_path=tmp_path / "missing-dir" / "x.rrd")
    assert manager.find("liveview") is None
    manager.shutdown()


def _fill_slots(ctx: RuntimeContext, k: int) -> None:
    t = time.time_ns()
    st = ctx.state
    st.imu.write(ImuSample(t, k % 100, (0.1, -0.2, 0.05), (0.3, 0.0, -9.8)))
    st.gps.write(GpsFix(t, 43200.0 + k, 43.68 + k * 1e-5, 10.39, 300.0 + k, 1, 9, hdop=0.9,
                        course_deg=5.0, alt_std_m=1.2, latency_s=0.02))
    st.servo.write(ServoState(t, k % 256, (1500,) * 8, (1510,) * 8, False, False, False, 99, 97))
    st.estimator.write(EstimatorState(t, (1.0, 0.0, 0.0, 0.0), 0.1, 0.05, 0.2, (k * 5.0, 0.0, -k * 1.0),
                                      (50.0, 0.0, 0.0), (0.0,) * 3, (0.0,) * 3, 43.68, 10.39, 300.0))


def test_view_thread_samples_slots_and_camera_frames(tmp_path: Path) -> None:
    ctx = RuntimeContext(flight_dir=tmp_path)
    rrd = tmp_path / "unit.rrd"
    view = LiveViewThread(save_path=rrd)
    view.ctx = ctx
    view.setup()
    image = np.zeros((48, 64, 3), dtype=np.uint8)

    class Horizon:
        found, p1, p2 = True, (0.0, 30.0), (63.0, 20.0)

    try:
        for k in range(12):
            _fill_slots(ctx, k)
            assert view.step() is True
            assert view.step() is True  # nothing new: nothing logged twice
        t0 = time.monotonic()
        for k in range(50):  # a flood of frames never blocks and keeps only the newest few
            view.frames.put((time.time_ns(), image + k, Horizon()))
        assert time.monotonic() - t0 < 0.5 and len(view.frames) <= 4
        view.step()
        view.cleanup()
    finally:
        view.close()
    rows = rows_per_entity(rrd)
    for entity in (E.IMU_RATES, E.SERVO_PILOT, E.ATTITUDE_ESTIMATE, E.AIRCRAFT, E.GPS_FIX):
        assert rows["/" + entity] == 12, entity
    assert rows["/" + E.CAMERA_IMAGE] == 1 and rows["/" + E.CAMERA_HORIZON] == 1
    assert column(rrd, "/" + E.SERVO_PILOT, "Scalars:scalars")[0] == [1500.0] * 8
    track = column(rrd, "/" + E.AIRCRAFT, "Transform3D:translation")
    north = [p[0][0] for p in track]  # estimator origin == first GPS fix: positions pass through
    assert north == pytest.approx([k * 5.0 for k in range(12)], abs=0.01)


def test_log_tail_follows_a_growing_file(live: LiveRun, tmp_path: Path) -> None:
    src = (live.flight_dir / "truth.bin").read_bytes()
    grown = tmp_path / "truth.bin"
    tail = LogTail(grown, 1)
    assert tail.poll() is None  # not there yet
    got = []
    cuts = np.linspace(0, len(src), 13).astype(int)  # cuts fall inside records
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        with open(grown, "ab") as f:
            f.write(src[a:b])
        data = tail.poll()
        if data is not None:
            got.append(data["time_s"])
    times = np.concatenate(got)
    expected = load_flight(live.flight_dir).block("truth", 1)
    assert expected is not None
    assert np.array_equal(times, expected["time_s"])


_SERVE_SCRIPT = """
import sys
from companion.liveview import open_recording
rec = open_recording(serve=True, grpc_port=int(sys.argv[1]), web_port=int(sys.argv[2]),
                     serve_host="127.0.0.1")
print(rec.url, flush=True)
sys.stdin.read()
rec.close()
"""


def test_serve_accepts_viewers() -> None:
    # in a process of its own: rerun's servers live until their process exits, and in this one
    # their threads would open descriptors while later tests check for leaks
    grpc_port, web_port = free_tcp_port(), free_tcp_port()
    proc = subprocess.Popen([sys.executable, "-c", _SERVE_SCRIPT, str(grpc_port), str(web_port)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdin is not None
        ready, _, _ = select.select([proc.stdout], [], [], 60.0)
        assert ready, "the serving process printed no URL within 60 s"
        url = proc.stdout.readline().strip()
        assert str(grpc_port) in url and url.startswith("rerun+http://127.0.0.1:"), url
        for port in (grpc_port, web_port):
            with socket.create_connection(("127.0.0.1", port), timeout=5.0):
                pass
        proc.stdin.close()
        assert proc.wait(timeout=30.0) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10.0)
        for stream in (proc.stdin, proc.stdout):
            if stream is not None:
                stream.close()
