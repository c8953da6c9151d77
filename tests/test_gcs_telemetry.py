"""State-to-MAVLink scaling, health bits and the stream scheduler, without threads or sockets."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import pytest

from companion.core.clock import Clock
from companion.core.params import ParamRegistry
from companion.core.state import EstimatorState, GpsFix, ImuSample, ImuSlowSample, ServoState
from companion.estimation.thread import EstimatorThread
from companion.watchdog import ManagedThread, RuntimeContext, ThreadManager
from gcs_bridge import status, streams, telemetry
from gcs_bridge.bridge_params import BRIDGE_PARAMS
from gcs_bridge.dialect import UINT16_MAX, Identity, mavlink
from gcs_bridge.runtime_view import BridgeCore

ORIGIN = (43.7, 10.4, 50.0)


def make_core(*threads: ManagedThread) -> BridgeCore:
    ctx = RuntimeContext(clock=Clock(), params=ParamRegistry(), vehicle_id=7)
    ctx.params.declare_all(BRIDGE_PARAMS)
    manager = ThreadManager(ctx, list(threads))
    return BridgeCore(ctx, manager)


def est(pos: tuple[float, float, float] = (0.0, 0.0, 0.0), yaw: float = 0.0,
        origin: tuple[float, float, float] | None = ORIGIN, t_ns: int = 0) -> EstimatorState:
    o = origin or (None, None, None)
    return EstimatorState(t_ns, (1.0, 0.0, 0.0, 0.0), 0.1, -0.05, yaw, pos, (10.0, -2.0, 1.0),
                          (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), o[0], o[1], o[2],
                          rates_rad_s=(0.01, 0.02, 0.03), aligned=True)


def packs(msgs: list[Any]) -> list[Any]:
    """Every builder output must pack (field ranges) and parse back."""
    out = []
    for m in msgs:
        frame = m.pack(mavlink.MAVLink(None, 7, 1))
        out.append(mavlink.MAVLink(None, 0, 0).parse_char(frame))
    return out


# ------------------------------------------------------------------------------------ scaling
def test_global_position_is_scaled_from_the_estimate() -> None:
    core = make_core()
    (gp,) = packs(telemetry.global_position_int(core, est((1000.0, 0.0, -100.0), yaw=-math.pi / 2)))
    assert gp.lat == pytest.approx((ORIGIN[0] + 1000.0 / 111_132.0) * 1e7, abs=2_000)
    assert gp.lon == pytest.approx(ORIGIN[1] * 1e7, abs=10)
    # the tangent plane leaves the ellipsoid: 1 km north is ~8 cm higher above it
    assert gp.alt == pytest.approx((ORIGIN[2] + 100.0 + 0.0785) * 1000, abs=5)
    assert gp.relative_alt == 100_000
    assert (gp.vx, gp.vy, gp.vz) == (1000, -200, 100)
    assert gp.hdg == 27000
    assert telemetry.global_position_int(core, est(origin=None)) == []


def test_attitude_local_position_vfr_and_home() -> None:
    core = make_core()
    e = est((5.0, 6.0, -7.0))
    (att,) = packs(telemetry.attitude(core, e))
    assert (att.roll, att.pitch) == (pytest.approx(0.1), pytest.approx(-0.05))
    assert att.yawspeed == pytest.approx(0.03)
    (q,) = packs(telemetry.attitude_quaternion(core, e))
    assert (q.q1, q.q2) == (1.0, 0.0)
    (lp,) = packs(telemetry.local_position_ned(core, e))
    assert (lp.x, lp.y, lp.z, lp.vz) == (5.0, 6.0, -7.0, 1.0)
    (hud,) = packs(telemetry.vfr_hud(core, e, 0.42))
    assert hud.throttle == 42 and hud.groundspeed == pytest.approx(math.hypot(10, 2))
    assert hud.climb == pytest.approx(-1.0)
    assert telemetry.home_position(core) == []  # no estimate, no configured home
    core.ctx.home_lla = (1.0, 2.0, 3.0)
    (home,) = packs(telemetry.home_position(core))
    assert (home.latitude, home.longitude, home.altitude) == (10_000_000, 20_000_000, 3000)
    core.ctx.state.estimator.write(e)  # the estimator's origin wins
    (home,) = packs(telemetry.home_position(core))
    assert home.latitude == round(ORIGIN[0] * 1e7) and home.altitude == 50_000


def test_gps_unknowns_use_the_unknown_markers() -> None:
    core = make_core()
    fix = GpsFix(0, None, None, None, None, 0, None)
    msgs = packs(telemetry.gps_raw_int(core, fix))
    assert len(msgs) == 1
    g = msgs[0]
    assert g.fix_type == mavlink.GPS_FIX_TYPE_NO_FIX
    assert (g.eph, g.epv, g.vel, g.cog, g.satellites_visible) == (UINT16_MAX,) * 4 + (255,)
    fix = GpsFix(0, 1.0, 43.7, 10.4, 40.0, 2, 11, hdop=0.8, pdop=1.5, vdop=1.2, tdop=0.7,
                 speed_m_s=21.5, course_deg=359.996, alt_std_m=3.0, h_std_m=1.25)
    g, pdop, tdop = packs(telemetry.gps_raw_int(core, fix))
    assert g.fix_type == mavlink.GPS_FIX_TYPE_DGPS
    assert (g.lat, g.alt, g.eph, g.epv, g.vel, g.satellites_visible) == (437_000_000, 40_000, 80, 120,
                                                                         2150, 11)
    assert g.cog == 0  # 359.996 deg rounds to 36000 cdeg, which is 0
    assert (g.h_acc, g.v_acc) == (1250, 3000)
    assert (pdop.name, pdop.value, tdop.name) == ("GPS_PDOP", pytest.approx(1.5), "GPS_TDOP")
    assert g.yaw == 0  # a single-antenna receiver has no yaw


def test_gps_yaw_carries_a_dual_antenna_heading_on_the_airframe() -> None:
    core = make_core()
    fix = GpsFix(0, 1.0, 43.7, 10.4, 40.0, 1, 11, course_deg=10.0, heading_deg=359.996)
    g, *_ = packs(telemetry.gps_raw_int(core, fix))
    assert g.yaw == 36000 and g.cog == 1000  # north is 36000: 0 means "no yaw"
    # with the estimator's parameters: antennas across the wings, the airframe is 90 deg less
    core.ctx.params.declare_all(EstimatorThread.declare_params("EST"))
    core.ctx.params.set("EST_HDG_OFS", math.pi / 2)
    g, *_ = packs(telemetry.gps_raw_int(core, fix))
    assert g.yaw == 27000


def test_imu_messages() -> None:
    core = make_core()
    imu = ImuSample(0, 1, (0.1, -0.2, 0.3), (1.0, 2.0, -9.80665))
    (h,) = packs(telemetry.highres_imu(core, imu, None))
    assert (h.xgyro, h.zacc) == (pytest.approx(0.1), pytest.approx(-9.80665))
    assert h.fields_updated == 0x3F and math.isnan(h.temperature)
    slow = ImuSlowSample(0, (0, 0, 0), (0, 0, 0), 0.0, 0)
    (h,) = packs(telemetry.highres_imu(core, imu, slow))
    assert h.fields_updated & (1 << 12) and h.temperature == 0.0
    (s,) = packs(telemetry.scaled_imu(core, imu, slow))
    assert (s.zacc, s.xgyro, s.temperature) == (-1000, 100, 1)  # 0 degC is sent as 0.01
    (s,) = packs(telemetry.scaled_imu(core, imu, None))
    assert s.temperature == 0


def test_servo_board_messages_and_batteries() -> None:
    core = make_core()
    servo = ServoState(0, 1, (1500,) * 8, (1100, 1900, 0, 0, 0, 0, 0, 0), True, False, True,
                       100, 85)
    (rc,) = packs(telemetry.rc_channels(core, servo))
    assert rc.chancount == 8 and rc.chan8_raw == 1500 and rc.chan9_raw == UINT16_MAX
    assert rc.rssi == 0  # failsafe: no radio
    (out,) = packs(telemetry.servo_output_raw(core, servo))
    assert (out.servo1_raw, out.servo2_raw, out.servo3_raw) == (1100, 1900, 0)
    b1, b2 = packs(telemetry.battery_status(core, servo))
    assert (b1.id, b1.voltages[0], b1.battery_remaining) == (0, 8400, 100)
    assert b1.battery_function == mavlink.MAV_BATTERY_FUNCTION_AVIONICS
    assert (b2.id, b2.voltages[0], b2.battery_remaining) == (1, 4760, 25)
    assert b2.charge_state == mavlink.MAV_BATTERY_CHARGE_STATE_OK
    core.ctx.params.set("MAV_B_LOW_PCT", 30)
    _, b2 = packs(telemetry.battery_status(core, servo))
    assert b2.charge_state == mavlink.MAV_BATTERY_CHARGE_STATE_LOW
    assert telemetry.battery_percent(70, 80) == 0 and telemetry.battery_percent(120, 80) == 100


def test_extreme_values_still_pack() -> None:
    core = make_core()
    e = EstimatorState(0, (1.0, 0.0, 0.0, 0.0), 0.0, 0.0, float("nan"), (1e12, -1e12, 1e9),
                       (1e9, float("inf"), -1e9), (0, 0, 0), (0, 0, 0), 89.9, 179.9, 1e7)
    for build in (telemetry.global_position_int, telemetry.local_position_ned, telemetry.attitude):
        packs(build(core, e))
    core.ctx.state.estimator.write(e)
    packs(telemetry.home_position(core))
    packs(telemetry.vfr_hud(core, e, float("nan")))
    fix = GpsFix(0, 0.0, 95.0, 400.0, 1e12, 7, 10_000, hdop=1e9, speed_m_s=-5.0, h_std_m=1e12)
    packs(telemetry.gps_raw_int(core, fix))
    servo = ServoState(0, 0, (70000, -5) + (1500,) * 20, (99999,) * 20, False, False, False, 255, 0)
    packs(telemetry.rc_channels(core, servo) + telemetry.servo_output_raw(core, servo)
          + telemetry.battery_status(core, servo))


# ------------------------------------------------------------------------------------ identity
class Idle(ManagedThread):
    pass


def test_heartbeat_identity_and_boot_state() -> None:
    core = make_core(Idle("imu", thread_id=1))
    (hb,) = packs([status.heartbeat(core)])
    # the default claim is the honest one: a generic autopilot, the mode in the base flags only
    assert (hb.type, hb.autopilot, hb.system_status) == (
        mavlink.MAV_TYPE_FIXED_WING, mavlink.MAV_AUTOPILOT_GENERIC, mavlink.MAV_STATE_BOOT)
    assert hb.custom_mode == 0 and not hb.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert hb.base_mode & mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
    (px4,) = packs([status.heartbeat(core, Identity.PX4)])
    assert px4.autopilot == mavlink.MAV_AUTOPILOT_PX4 and px4.custom_mode == 1 << 16
    assert px4.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert status.heartbeat(core, Identity.ARDUPILOT).autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    for identity in (Identity.GENERIC, Identity.PX4):
        caps = status.autopilot_version(core, identity).capabilities
        assert caps & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
        assert not caps & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
        assert caps & mavlink.MAV_PROTOCOL_CAPABILITY_FTP
    caps = status.autopilot_version(core, Identity.ARDUPILOT).capabilities
    assert caps & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST


def test_sensor_bits_follow_the_threads() -> None:
    # a thread stands for what its row publishes, whatever its id
    core = make_core(Idle("imu", thread_id=1, publishes=("imu",)),
                     Idle("gps", thread_id=12, publishes=("gps",)),
                     Idle("servo", thread_id=3, publishes=("servo",)), Idle("other", thread_id=4))
    core.ctx.params.set("GPS_ENABLE", 0)
    present, enabled, healthy = status.sensor_bits(core)
    gps = mavlink.MAV_SYS_STATUS_SENSOR_GPS
    gyro = mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
    batt = mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
    assert present & gps and not enabled & gps and enabled & gyro and present & batt
    # nothing has run yet; only the absent geofence is "not breached" (MAVProxy reads a clear
    # GEOFENCE health bit as a breach and says so on connecting)
    assert healthy == mavlink.MAV_SYS_STATUS_GEOFENCE
    assert not present & mavlink.MAV_SYS_STATUS_GEOFENCE
    assert not present & mavlink.MAV_SYS_STATUS_AHRS  # id 4 publishes no estimate


def test_thread_status_names_fit_ten_characters() -> None:
    t = Idle("a-thread-with-a-long-name", thread_id=42, param_prefix="LONG")
    core = make_core(t)
    msgs = packs(status.thread_status_messages(core, t.status()))
    assert [m.name for m in msgs] == ["T42_LEDS", "T42_RST", "T42_STEPUS", "T42_WDGMS", "T42_MSGMS"]
    assert all(len(m.name) <= 10 for m in msgs)
    assert msgs[3].value == 500


# ------------------------------------------------------------------------------------ scheduler
@dataclass
class FakeLink:
    index: int = 0
    counters: status.LinkCounters = field(default_factory=status.LinkCounters)
    sent: list[tuple[int, str]] = field(default_factory=list)
    now_ns: int = 0
    identity: Identity = Identity.GENERIC

    def next_thread_status(self) -> Any:
        return None

    def emit(self, msgs: list[Any]) -> None:
        self.sent += [(self.now_ns, m.get_type()) for m in msgs]


def only(specs_ids: list[int]) -> list[streams.StreamSpec]:
    return [streams.STREAMS_BY_ID[i] for i in specs_ids]


def test_data_stream_waits_for_a_sample_newer_than_its_due_time() -> None:
    core = make_core()
    sched = streams.StreamScheduler(core, only([mavlink.MAVLINK_MSG_ID_ATTITUDE]))
    link = FakeLink()
    ms = 1_000_000
    # no data ever: nothing sent, looked at again one default (20 Hz) period later
    assert sched.service(0, link, link.emit) == 50 * ms
    core.ctx.state.estimator.write(est())
    sched.set_interval(mavlink.MAVLINK_MSG_ID_ATTITUDE, 100_000, 0)  # 10 Hz
    sched.service(0, link, link.emit)
    assert len(link.sent) == 1  # first one at once
    wait = sched.service(100 * ms, link, link.emit)  # due, but the sample is old
    assert len(link.sent) == 1 and wait == streams.AWAIT_NS
    assert sched.awaited is not None and sched.awaited[0] is core.ctx.state.estimator
    core.ctx.state.estimator.write(est())
    link.now_ns = 103 * ms
    wait = sched.service(103 * ms, link, link.emit)
    assert link.sent[-1] == (103 * ms, "ATTITUDE")
    assert wait == 97 * ms  # next due keeps the 100 ms grid (200 ms), not 103 + 100
    # a period without any new sample is skipped, not filled with stale data
    sched.service(200 * ms, link, link.emit)
    sched.service(300 * ms, link, link.emit)
    assert len(link.sent) == 2 and link.counters.stale_skips == 1


def test_intervals_override_disable_and_default() -> None:
    core = make_core()
    hb = mavlink.MAVLINK_MSG_ID_HEARTBEAT
    sched = streams.StreamScheduler(core, only([hb]))
    link = FakeLink()
    t = 0
    while t <= 3_000_000_000:  # 3 s of heartbeats at the default 1 Hz
        sched.service(t, link, link.emit)
        t += 10_000_000
    assert len(link.sent) == 4
    assert sched.interval_us(hb) == 1_000_000
    assert sched.set_interval(hb, 250_000, t)
    n = len(link.sent)
    for _ in range(100):
        sched.service(t, link, link.emit)
        t += 10_000_000
    assert len(link.sent) - n == 4
    assert sched.set_interval(hb, -1, t) and sched.interval_us(hb) == -1
    n = len(link.sent)
    for _ in range(100):
        sched.service(t, link, link.emit)
        t += 10_000_000
    assert len(link.sent) == n
    assert sched.set_interval(hb, 0, t) and sched.interval_us(hb) == 1_000_000
    assert sched.set_interval(hb, 10, t) and sched.interval_us(hb) == streams.MIN_INTERVAL_US
    assert not sched.set_interval(mavlink.MAVLINK_MSG_ID_MISSION_ITEM, 1000, t)


def test_stream_defaults_are_a_ground_stations_rates_not_the_threads_periods() -> None:
    core = make_core(Idle("estimator", thread_id=4, message_ms=1000, param_prefix="EST"))
    sched = streams.StreamScheduler(core)
    # a HUD at 20 Hz although the estimator's (legacy) message period is 1 s
    assert sched.interval_us(mavlink.MAVLINK_MSG_ID_ATTITUDE) == 50_000
    assert sched.interval_us(mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION) == 50_000
    assert sched.interval_us(mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT) == 200_000
    assert sched.interval_us(mavlink.MAVLINK_MSG_ID_VFR_HUD) == 200_000
    assert sched.interval_us(mavlink.MAVLINK_MSG_ID_GPS_RAW_INT) == 500_000
    assert sched.interval_us(mavlink.MAVLINK_MSG_ID_SYS_STATUS) == 500_000
    assert sched.interval_us(mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE) == 500_000
    core.ctx.params.set("EST_MSG_MS", 40)  # paces the legacy protocol only
    assert sched.interval_us(mavlink.MAVLINK_MSG_ID_ATTITUDE) == 50_000
    core.ctx.params.set("MAV_POS_HZ", 25.0)  # the user's default, persisted like any parameter
    assert sched.interval_us(mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT) == 40_000
    core.ctx.params.set("MAV_IMU_HZ", 0.0)
    assert sched.interval_us(mavlink.MAVLINK_MSG_ID_HIGHRES_IMU) == -1
    assert sched.interval_us(mavlink.MAVLINK_MSG_ID_SCALED_IMU) == -1  # off by default
    assert sched.interval_us(mavlink.MAVLINK_MSG_ID_NAMED_VALUE_FLOAT) == 1_000_000  # MGR_STATUS_MS
    groups = {s.msg_id for s in streams.streams_in_group(mavlink.MAV_DATA_STREAM_POSITION)}
    assert groups == {mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
                      mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED}


def test_a_shorter_message_period_applies_at_once() -> None:
    core = make_core(Idle("estimator", thread_id=4, message_ms=1000, param_prefix="EST"))
    core.ctx.params.set("MAV_ATT_HZ", 1.0)
    sched = streams.StreamScheduler(core, only([mavlink.MAVLINK_MSG_ID_ATTITUDE]))
    link = FakeLink()
    ms = 1_000_000
    core.ctx.state.estimator.write(est())
    sched.service(0, link, link.emit)
    assert len(link.sent) == 1
    core.ctx.params.set("MAV_ATT_HZ", 10.0)
    sched.service(150 * ms, link, link.emit)  # periods re-read: next one due at 250 ms
    sched.service(250 * ms, link, link.emit)  # due: waits for the next sample
    core.ctx.state.estimator.write(est())
    sched.service(255 * ms, link, link.emit)
    assert len(link.sent) == 2  # not after the rest of the old 1 s period


def _load_bytes_s(sched: streams.StreamScheduler) -> float:
    return sum(streams.frame_bytes(spec) * 1e6 / sched.interval_us(spec.msg_id)
               for spec in streams.STREAMS if sched.interval_us(spec.msg_id) > 0)


@pytest.mark.parametrize("baud", [9600, 57600, 115200])
def test_a_radios_default_schedule_fits_its_share_of_the_line(baud: int) -> None:
    core = make_core()
    link = FakeLink()
    sched = streams.StreamScheduler(core, line_bytes_s=baud / 10.0)
    network = streams.StreamScheduler(core)
    sched.service(1, link, link.emit)
    network.service(1, link, link.emit)
    share = baud / 10.0 * core.ctx.params.get("MAV_RADIO_PCT") / 100.0
    if baud >= 115200:  # the whole network schedule fits: nothing is cut
        assert _load_bytes_s(network) <= share
        assert all(sched.interval_us(s.msg_id) == network.interval_us(s.msg_id)
                   for s in streams.STREAMS)
        return
    assert _load_bytes_s(network) > share  # the network schedule would not fit: it is fitted
    assert _load_bytes_s(sched) <= share * 1.01 or baud == 9600
    att = sched.interval_us(mavlink.MAVLINK_MSG_ID_ATTITUDE)
    assert att > network.interval_us(mavlink.MAVLINK_MSG_ID_ATTITUDE)  # the fastest give way
    assert sched.interval_us(mavlink.MAVLINK_MSG_ID_HEARTBEAT) == 1_000_000  # never cut
    if baud >= 57600:  # slow streams keep their rate while attitude is cut
        assert sched.interval_us(mavlink.MAVLINK_MSG_ID_GPS_RAW_INT) == 500_000
        assert att <= 250_000  # still a usable HUD: at least 4 Hz
    # a rate the user asked for is kept, and the rest is fitted around it
    sched.set_interval(mavlink.MAVLINK_MSG_ID_ATTITUDE, 100_000, 2)
    sched.service(200_000_002, link, link.emit)
    assert sched.interval_us(mavlink.MAVLINK_MSG_ID_ATTITUDE) == 100_000


def test_fit_to_line_cuts_the_fastest_first() -> None:
    rates = streams.fit_to_line([20.0, 2.0, 1.0], [100, 100, 100], [False, False, True], 700.0)
    assert rates[2] == 1.0 and rates[1] == 2.0 and rates[0] == pytest.approx(4.0)
    assert streams.fit_to_line([1.0, 2.0], [10, 10], [False, False], 1e6) == [1.0, 2.0]
    tiny = streams.fit_to_line([20.0, 2.0], [100, 100], [False, False], 1.0)
    assert tiny == [streams.MIN_FITTED_HZ, streams.MIN_FITTED_HZ]


def test_a_sources_period_is_learnt_from_its_write_stamps() -> None:
    """The sender sleeps until a sample is expected rather than polling for it: the period
    comes from the slot's stamps once a few writes were seen, and a quiet source is looked at
    once per period, not every millisecond."""
    rate = streams._SourceRate()
    ms = 1_000_000
    rate.observe(1, 1000 * ms)
    assert rate.next_host_ns(1001 * ms) is None  # one write: no period yet
    for v in range(2, 2 + streams.RATE_INTERVALS):
        rate.observe(v, 1000 * ms + (v - 1) * 10 * ms)  # 100 Hz
    last = 1000 * ms + streams.RATE_INTERVALS * 10 * ms
    assert rate.period_ns == 10 * ms
    assert rate.next_host_ns(last + 2 * ms) == last + 10 * ms
    assert rate.first_after_host_ns(last + 25 * ms) == last + 30 * ms
    assert rate.next_host_ns(last + 50 * ms) == last + 60 * ms  # late by > a period: quiet
    rate.observe(rate.version + 2, last + 20 * ms)  # two writes between two looks
    assert rate.period_ns == 10 * ms
