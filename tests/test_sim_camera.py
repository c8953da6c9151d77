"""The simulated camera: frames at the true attitude, the real detector, the real legacy path.

Signs are checked against the truth (a right bank must read as a positive roll, nose up as a
positive pitch), accuracy on clean frames, failures counted where no horizon is in view,
determinism for a seed, the offline hand-off ticks, and the datagram path: decoded by the legacy
codec from a real UDP socket, and accepted by the runtime's legacy adapter into
``state.horizon``.
"""

from __future__ import annotations

import math
import socket
import threading

import numpy as np
import pytest
from conftest import free_udp_port

from companion.core.clock import Clock
from companion.core.params import ParamRegistry
from companion.sim.camera import OfflineCameraFeed, SimCamera, horizon_measurements
from companion.sim.world_camera import LegacyHorizonLink, SlotLink, WorldCamera, attach_camera
from companion.watchdog import RuntimeContext, ThreadManager
from horizon.camera import CameraModel
from legacy_protocol import codec, messages
from legacy_protocol.adapter import LegacyAdapter

R = math.radians


def clean_camera(seed: int = 0, **kw: object) -> SimCamera:
    return SimCamera(seed, disturbance="none", track=False, **kw)  # type: ignore[arg-type]


@pytest.mark.parametrize("roll_deg", [15.0, -15.0])
def test_a_right_bank_reads_as_positive_roll(roll_deg: float) -> None:
    cam = clean_camera()
    r = cam.capture(0.05, R(roll_deg), 0.0)
    assert not r.failed
    assert math.copysign(1.0, math.degrees(r.roll_rad)) == math.copysign(1.0, roll_deg)
    # counter-clockwise in the image: for a right bank the right end of the line is higher
    assert r.estimate.p1 is not None and r.estimate.p2 is not None
    left, right = sorted([r.estimate.p1, r.estimate.p2])
    assert (right[1] < left[1]) == (roll_deg > 0)


@pytest.mark.parametrize("pitch_deg", [8.0, -8.0])
def test_nose_up_moves_the_horizon_down_and_reads_as_positive_pitch(pitch_deg: float) -> None:
    cam = clean_camera()
    r = cam.capture(0.05, 0.0, R(pitch_deg))
    assert not r.failed
    assert r.estimate.offset_frac is not None
    assert (r.estimate.offset_frac > 0) == (pitch_deg > 0)  # positive below the centre
    assert math.copysign(1.0, r.pitch_rad) == math.copysign(1.0, pitch_deg)


def test_clean_frames_give_roll_and_pitch_to_a_fraction_of_a_degree() -> None:
    cam = clean_camera(seed=4)
    for roll in (-60.0, -30.0, 0.0, 20.0, 45.0):
        for pitch in (-12.0, -3.0, 0.0, 5.0, 15.0):
            r = cam.capture(0.05, R(roll), R(pitch))
            assert not r.failed, (roll, pitch)
            assert abs(math.degrees(r.roll_error_rad)) < 0.5, (roll, pitch, r)
            assert abs(math.degrees(r.pitch_error_rad)) < 0.5, (roll, pitch, r)
            assert 0.0 < r.quality <= 1.0
    s = cam.stats.summary()
    assert s["frames"] == 25 and s["failures"] == 0 and s["gross"] == 0


def test_inverted_flight_reads_about_180_deg_of_roll() -> None:
    r = clean_camera().capture(0.05, R(170.0), R(4.0))
    assert not r.failed
    assert abs(math.degrees(r.roll_error_rad)) < 1.0
    assert abs(math.degrees(r.pitch_error_rad)) < 1.0


def test_a_lens_with_distortion_is_rendered_and_corrected() -> None:
    lens = CameraModel.from_hfov(160, 120, 90.0, k1=-0.2, k2=0.03)
    r = clean_camera(camera=lens).capture(0.05, R(12.0), R(-6.0))
    assert not r.failed
    assert abs(math.degrees(r.roll_error_rad)) < 1.0
    assert abs(math.degrees(r.pitch_error_rad)) < 1.0


@pytest.mark.parametrize("pitch_deg", [-60.0, 60.0])
def test_no_horizon_in_view_is_a_counted_failure_and_sends_nothing(pitch_deg: float) -> None:
    cam = clean_camera()
    r = cam.capture(0.05, R(5.0), R(pitch_deg))
    assert r.failed and math.isnan(r.roll_rad) and r.quality == 0.0
    assert r.measurement(0) is None
    assert not r.gross
    assert cam.stats.failures == 1 and cam.stats.detections == 0
    assert not r.in_view and cam.stats.missed == 0  # nothing to see: a right answer


def test_the_same_seed_gives_the_same_frames_and_answers() -> None:
    def run(seed: int) -> list[tuple[float, float, float, tuple[str, ...]]]:
        cam = SimCamera(seed, disturbance="thesis", scene="varying", scene_change_s=1.0)
        rng = np.random.default_rng(0)
        out = []
        for i in range(30):
            r = cam.capture(0.1 * i + 0.05, R(rng.uniform(-30, 30)), R(rng.uniform(-8, 8)))
            out.append((r.roll_rad, r.pitch_rad, r.quality, r.disturbances))
        return out

    a, b = run(7), run(7)
    assert str(a) == str(b)  # NaN-safe equality
    assert str(run(8)) != str(a)


def test_a_frame_depends_on_its_number_not_on_the_frames_before_it() -> None:
    a = SimCamera(3, disturbance="thesis", track=False)
    b = SimCamera(3, disturbance="thesis", track=False)
    for i in range(5):
        a.capture(0.1 * i, R(10.0), 0.0)
    ra = a.capture(1.0, R(-20.0), R(3.0), index=42)
    rb = b.capture(1.0, R(-20.0), R(3.0), index=42)
    assert str((ra.roll_rad, ra.pitch_rad, ra.disturbances)) == \
        str((rb.roll_rad, rb.pitch_rad, rb.disturbances))


def test_frames_fall_mid_period_and_are_handed_off_after_the_latency() -> None:
    cam = clean_camera(rate_hz=10.0, latency_s=0.1)
    t_s = (np.arange(100) + 1.0) * 0.01  # one second of 100 Hz ticks, as record_flight
    euler = np.zeros((100, 3))
    euler[:, 0] = R(10.0)
    out = horizon_measurements(cam, t_s, euler)
    assert cam.stats.frames == 10
    # frames at 0.05, 0.15, ... 0.95 s; hand-off 0.1 s later, so the last one is still pending
    assert sorted(out) == [k - 1 for k in range(15, 100, 10)]
    for k, m in out.items():
        assert m.t_ns == round((t_s[k] - 0.1) * 1e9)
        assert m.source == "sim_camera"
        assert abs(math.degrees(m.roll_rad) - 10.0) < 0.5


def test_the_offline_feed_skips_to_the_latest_frame_when_ticks_jump() -> None:
    feed = OfflineCameraFeed(clean_camera(rate_hz=10.0, latency_s=0.0))
    assert feed.step(0.05, 0.0, 0.0) is not None
    assert feed.step(0.06, 0.0, 0.0) is None
    assert feed.step(1.0, 0.0, 0.0) is not None  # frames 1..8 skipped, 9 taken
    assert feed.camera.stats.frames == 2


def _receiver() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(2.0)
    return s


def test_the_datagram_is_the_legacy_horizon_attitude_and_decodes() -> None:
    rx = _receiver()
    link = LegacyHorizonLink("127.0.0.1", rx.getsockname()[1], vehicle_id=7,
                             clock_ns=lambda: 1_700_000_000_500_000_000)
    try:
        r = clean_camera().capture(0.05, R(20.0), R(4.0))
        assert link(r, 1_700_000_000_123_456_789)
        data, _ = rx.recvfrom(2048)
        decoded = codec.decode(data)
        assert isinstance(decoded, codec.Decoded)
        assert decoded.header.type_code == messages.MsgType.HORIZON_ATTITUDE
        assert decoded.header.vehicle_id == 7 and len(data) == 36
        p = decoded.payload
        assert isinstance(p, messages.HorizonAttitude)
        assert p.frame_t_ns == 1_700_000_000_123_456_789
        assert math.isclose(p.roll_rad, r.roll_rad, abs_tol=1e-6)
        assert math.isclose(p.pitch_rad, r.pitch_rad, abs_tol=1e-6)
        assert math.isclose(p.quality, r.quality, abs_tol=1e-6)
        failed = clean_camera().capture(0.05, 0.0, R(-70.0))
        assert not link(failed, 0)  # a failure is not sent
        rx.settimeout(0.05)
        with pytest.raises(TimeoutError):
            rx.recvfrom(2048)
    finally:
        link.close()
        rx.close()


def test_the_runtime_legacy_adapter_writes_the_camera_to_the_estimator_slot() -> None:
    ctx = RuntimeContext(clock=Clock(), params=ParamRegistry(), vehicle_id=2)
    port = free_udp_port()
    adapter = LegacyAdapter(ctx, ThreadManager(ctx, []), dest=f"127.0.0.1:{free_udp_port()}",
                            listen_port=port, bind_host="127.0.0.1")
    cam = attach_camera(f"127.0.0.1:{port}", ctx.clock, vehicle_id=2, seed=1, threaded=False,
                        disturbance="none", latency_s=0.05)
    try:
        roll, pitch = R(-25.0), R(6.0)
        for k in range(30):  # 0.3 s of 100 Hz ticks: frames at 0.05, 0.15, 0.25 s
            cam.on_tick((k + 1) * 0.01, roll, pitch)
        assert cam.stats.frames == 3 and cam.stats.sent == 3
        for _ in range(3):
            adapter.receive_once(timeout_s=2.0)
        assert adapter.counters.accepted == 3 and adapter.counters.malformed == 0
        h = ctx.state.horizon.read()
        assert h is not None and h.source == "legacy"
        assert abs(math.degrees(h.roll_rad - roll)) < 0.5
        assert abs(math.degrees(h.pitch_rad - pitch)) < 0.5
        assert 0.0 < h.quality <= 1.0
        assert abs(h.t_ns - ctx.clock.realtime_ns()) < 5e9  # the runtime's timebase
    finally:
        summary = cam.close()
        adapter.close()
    assert summary["sent"] == 3 and summary["failures"] == 0


def test_a_lockstep_world_writes_the_slot_directly_on_the_same_schedule() -> None:
    ctx = RuntimeContext(clock=Clock(), params=ParamRegistry())
    cam = WorldCamera(clean_camera(latency_s=0.05), SlotLink(ctx.state.horizon), ctx.clock,
                      threaded=False)
    for k in range(9):
        cam.on_tick((k + 1) * 0.01, R(5.0), R(1.0))
    assert ctx.state.horizon.read() is None  # the frame at 0.05 s is handed off at 0.10 s
    cam.on_tick(0.10, R(5.0), R(1.0))
    h = ctx.state.horizon.read()
    assert h is not None and h.source == "legacy" and abs(math.degrees(h.roll_rad) - 5.0) < 0.5
    assert cam.close()["sent"] == 1


def test_the_camera_thread_hands_off_no_earlier_than_the_latency() -> None:
    rx = _receiver()
    clock = Clock(scale=2.0)
    link = LegacyHorizonLink("127.0.0.1", rx.getsockname()[1], clock_ns=clock.realtime_ns)
    sim = SimCamera(2, disturbance="light", latency_s=0.1)
    sim.render(0.0, 0.0, 0.0, np.random.default_rng(0))  # the scene, rendered once per flight
    cam = WorldCamera(sim, link, clock)
    try:
        t0 = clock.monotonic_ns()
        k = 0
        never = threading.Event()
        while clock.monotonic_ns() - t0 < 1.0e9:  # one second of flight at 2x
            k += 1
            clock.sleep(0.01, never)
            cam.on_tick(k * 0.01, R(10.0), 0.0)
        clock.sleep(0.3, never)  # the last frame's hand-off
    finally:
        summary = cam.close()  # joins the camera thread: every send is done
    ages: list[float] = []
    try:
        rx.settimeout(0.2)
        while True:
            try:
                data, _ = rx.recvfrom(2048)
            except TimeoutError:
                break
            d = codec.decode(data)
            assert isinstance(d, codec.Decoded) and isinstance(d.payload, messages.HorizonAttitude)
            ages.append((d.header.t_ns - d.payload.frame_t_ns) / 1e9)
    finally:
        rx.close()
    assert summary["frames"] >= 5  # 10 due; a loaded machine may drop some, never all
    assert len(ages) == summary["sent"] >= 3
    assert min(ages) >= 0.1 - 1e-3  # sent at frame time + latency (clock seconds) or later


def test_the_estimator_fuses_the_cameras_measurements() -> None:
    from companion.evaluation.sitl import FlightSpec, record_flight
    from companion.evaluation.sitl_estimator import EskfOptions, run_eskf

    rec = record_flight(FlightSpec(duration_s=20.0, scenario="turns", seed=1))
    cam = SimCamera(1, disturbance="light")
    rec.horizon = horizon_measurements(cam, rec.t_s, rec.euler_true_rad)
    assert len(rec.horizon) >= 190
    run = run_eskf(rec, EskfOptions(horizon=True))
    assert run.horizon_used >= 0.9 * len(rec.horizon)  # the filter takes them, its gate passes
    assert cam.stats.summary()["failure_pct"] < 5.0
