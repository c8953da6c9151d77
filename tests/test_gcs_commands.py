"""Identity, telemetry rates and commands with a raw MAVLink client, against a SyntheticVehicle.

Every test runs the MAVLink bridge on a `support.synthetic_vehicle.SyntheticVehicle`: synthetic
vehicle state (an aircraft in a steady banked circle) under a real ThreadManager, in this
process. No drivers, estimator, control law or simulator run, and the parameters are only
the manager's, the synthetic threads' and the bridge's (not the runtime's set) plus the
test's.

Reboot and shutdown commands end the SyntheticVehicle's manager run, not a runtime process.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest
from conftest import free_udp_port, wait_for
from support.synthetic_vehicle import MiniGcs, SyntheticVehicle

from gcs_bridge.commands import CMD_RESTART_THREAD
from gcs_bridge.dialect import MSG_ID_PROTOCOL_VERSION, mavlink
from gcs_bridge.services import ftp_wire

NAN = float("nan")


@contextmanager
def running(**kwargs: Any) -> Iterator[tuple[SyntheticVehicle, MiniGcs]]:
    gcs = MiniGcs(listen_port=free_udp_port())
    try:
        with SyntheticVehicle([f"udpout:127.0.0.1:{gcs.port}"], **kwargs) as v:
            assert gcs.recv(5.0, "HEARTBEAT") is not None
            yield v, gcs
    finally:
        gcs.close()


def command(gcs: MiniGcs, cmd: int, *params: float, use_int: bool = False) -> Any:
    """Send a command (unused parameters NaN, as MAVSDK does) and return its COMMAND_ACK."""
    p = list(params) + [NAN] * (7 - len(params))
    if use_int:
        msg = mavlink.MAVLink_command_int_message(1, 1, 0, cmd, 0, 0, p[0], p[1], p[2], p[3],
                                                  0 if math.isnan(p[4]) else int(p[4]),
                                                  0 if math.isnan(p[5]) else int(p[5]), p[6])
    else:
        msg = mavlink.MAVLink_command_long_message(1, 1, cmd, 0, *p)
    gcs.send(msg)
    return gcs.recv(3.0, "COMMAND_ACK", lambda m: m.command == cmd)


def rates(gcs: MiniGcs, duration_s: float) -> Counter[str]:
    return Counter(m.get_type() for m in gcs.collect(duration_s))


def test_identity_and_default_rates_a_ground_station_expects() -> None:
    with running(vehicle_id=7) as (v, gcs):
        hb = gcs.recv(2.0, "HEARTBEAT")
        assert (hb.get_srcSystem(), hb.get_srcComponent()) == (7, 1)
        assert (hb.type, hb.autopilot, hb.mavlink_version) == (
            mavlink.MAV_TYPE_FIXED_WING, mavlink.MAV_AUTOPILOT_GENERIC, 3)
        # nothing requested: the defaults (MAV_*_HZ), not the threads' 1 s message periods
        n = rates(gcs, 2.0)
        expected = {"HEARTBEAT": 2, "ATTITUDE": 40, "ATTITUDE_QUATERNION": 40,
                    "GLOBAL_POSITION_INT": 10, "LOCAL_POSITION_NED": 10, "VFR_HUD": 10,
                    "HIGHRES_IMU": 20, "GPS_RAW_INT": 4, "RC_CHANNELS": 8,
                    "SERVO_OUTPUT_RAW": 8, "BATTERY_STATUS": 8, "SYS_STATUS": 4,
                    "EXTENDED_SYS_STATE": 4}
        for name, count in expected.items():  # (BATTERY_STATUS: two batteries per send)
            assert count * 0.75 - 1 <= n[name] <= count * 1.25 + 1, (name, n[name], count)
        # the defaults are parameters (a user's choice persists); thread status keeps its own
        p = v.params
        for name, hz in [("MAV_POS_HZ", 20.0), ("MAV_HUD_HZ", 20.0), ("MAV_GPS_HZ", 5.0),
                         ("MAV_RC_HZ", 10.0), ("MAV_STAT_HZ", 20.0)]:
            p.set(name, hz)
        p.set("MGR_STATUS_MS", 250)
        gcs.collect(0.3)  # let the new periods take over
        n = rates(gcs, 2.0)
        expected = {"HEARTBEAT": 2, "ATTITUDE": 40, "ATTITUDE_QUATERNION": 40,
                    "GLOBAL_POSITION_INT": 40, "LOCAL_POSITION_NED": 40, "VFR_HUD": 40,
                    "HIGHRES_IMU": 20, "GPS_RAW_INT": 10, "RC_CHANNELS": 20,
                    "SERVO_OUTPUT_RAW": 20, "BATTERY_STATUS": 80, "SYS_STATUS": 40}
        for name, count in expected.items():
            assert count * 0.75 - 1 <= n[name] <= count * 1.25 + 1, (name, n[name], count)
        assert n["SCALED_IMU"] == 0
        # thread status: 4 named ints + 1 float per thread, one thread every 250 ms
        assert 6 <= n["NAMED_VALUE_FLOAT"] - n["GPS_RAW_INT"] * 2 <= 10
        status = hb.system_status
        assert status in (mavlink.MAV_STATE_BOOT, mavlink.MAV_STATE_STANDBY)
        assert wait_for(lambda: (h := gcs.recv(1.5, "HEARTBEAT")) is not None
                        and h.system_status == mavlink.MAV_STATE_STANDBY, 4.0)
        sys_status = gcs.recv(2.0, "SYS_STATUS")
        gyro = mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
        gps = mavlink.MAV_SYS_STATUS_SENSOR_GPS
        assert sys_status.onboard_control_sensors_present & gyro
        assert sys_status.onboard_control_sensors_health & (gyro | gps) == gyro | gps
        assert sys_status.voltage_battery == 8232 and sys_status.battery_remaining == 90


def test_set_message_interval_and_request_data_stream() -> None:
    with running() as (_v, gcs):
        att = mavlink.MAVLINK_MSG_ID_ATTITUDE
        assert command(gcs, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, att, 20_000).result == 0
        gcs.collect(0.2)
        assert 40 <= rates(gcs, 1.0)["ATTITUDE"] <= 60
        ack = command(gcs, mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, att)
        assert ack.result == 0
        assert gcs.recv(2.0, "MESSAGE_INTERVAL").interval_us == 20_000
        assert command(gcs, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, att, -1, use_int=True).result == 0
        gcs.collect(0.2)
        assert rates(gcs, 1.2)["ATTITUDE"] == 0
        assert command(gcs, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, att, 0).result == 0
        assert 18 <= rates(gcs, 1.0)["ATTITUDE"] <= 24  # back to the default 20 Hz
        assert command(gcs, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                       mavlink.MAVLINK_MSG_ID_MISSION_ITEM, 1000).result == \
            mavlink.MAV_RESULT_UNSUPPORTED
        assert command(gcs, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL).result == mavlink.MAV_RESULT_DENIED
        gcs.send(mavlink.MAVLink_request_data_stream_message(1, 1, mavlink.MAV_DATA_STREAM_POSITION,
                                                             10, 1))
        gcs.collect(0.2)
        n = rates(gcs, 1.0)
        # switched on at about 10 Hz: a busy machine may delay a message past the 1 s window
        # (7 were seen), never add one
        assert 6 <= n["GLOBAL_POSITION_INT"] <= 12 and 6 <= n["LOCAL_POSITION_NED"] <= 12
        gcs.send(mavlink.MAVLink_request_data_stream_message(1, 1, mavlink.MAV_DATA_STREAM_ALL, 0, 0))
        gcs.collect(0.2)
        n = rates(gcs, 1.2)
        assert n["GLOBAL_POSITION_INT"] == 0 and n["SYS_STATUS"] == 0 and n["HEARTBEAT"] >= 1


def test_information_requests() -> None:
    with running() as (_v, gcs):
        gcs.send(mavlink.MAVLink_command_long_message(
            1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
            NAN, NAN, NAN, NAN, NAN, NAN))
        first = gcs.recv(2.0, ("COMMAND_ACK", "AUTOPILOT_VERSION"))
        assert first.get_type() == "COMMAND_ACK" and first.result == 0  # ACK first
        ver = gcs.recv(2.0, "AUTOPILOT_VERSION")
        assert ver.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
        assert ver.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        assert command(gcs, mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1).result == 0
        assert gcs.recv(2.0, "AUTOPILOT_VERSION") is not None
        assert command(gcs, mavlink.MAV_CMD_REQUEST_PROTOCOL_VERSION, 1).result == 0
        pv = gcs.recv(2.0, f"UNKNOWN_{MSG_ID_PROTOCOL_VERSION}")  # not in pymavlink's dialect
        assert pv is not None and pv.get_msgbuf()[10:12] == b"\xc8\x00"  # version 200
        assert command(gcs, mavlink.MAV_CMD_GET_HOME_POSITION).result == 0
        home = gcs.recv(2.0, "HOME_POSITION")
        assert home is not None and abs(home.latitude - 437_085_000) < 10
        assert command(gcs, mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_GPS_RAW_INT).result == 0
        assert gcs.recv(2.0, "GPS_RAW_INT").fix_type == mavlink.GPS_FIX_TYPE_3D_FIX
        assert command(gcs, mavlink.MAV_CMD_REQUEST_MESSAGE, 99_999).result == \
            mavlink.MAV_RESULT_UNSUPPORTED
        # MESSAGE_INTERVAL by REQUEST_MESSAGE (param2 = the message asked about), as QGC asks
        assert command(gcs, mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_MESSAGE_INTERVAL,
                       mavlink.MAVLINK_MSG_ID_ATTITUDE).result == 0
        interval = gcs.recv(2.0, "MESSAGE_INTERVAL")
        assert (interval.message_id, interval.interval_us) == (mavlink.MAVLINK_MSG_ID_ATTITUDE, 50_000)
        # COMPONENT_METADATA, which QGC and MAVSDK ask for: where to fetch the descriptions
        assert command(gcs, mavlink.MAV_CMD_REQUEST_MESSAGE, 397).result == 0
        meta = gcs.recv(2.0, "COMPONENT_METADATA")
        assert meta is not None and meta.uri.startswith("mftp://") and meta.file_crc != 0
        assert command(gcs, mavlink.MAV_CMD_DO_SET_SERVO, 1, 1500).result == mavlink.MAV_RESULT_UNSUPPORTED
        gcs.send(mavlink.MAVLink_ping_message(123456, 9, 0, 0))
        pong = gcs.recv(2.0, "PING")
        assert (pong.time_usec, pong.seq, pong.target_system, pong.target_component) == (123456, 9, 255, 190)
        gcs.send(mavlink.MAVLink_timesync_message(0, 777))
        ts = gcs.recv(2.0, "TIMESYNC")
        assert ts.ts1 == 777 and ts.tc1 > 0
        body = ftp_wire.HEADER.pack(5, 0, ftp_wire.OP_OPEN_FILE_RO, 17, 0, 0, 0, 0) + b"@PARAM/param.pck"
        gcs.send(mavlink.MAVLink_file_transfer_protocol_message(0, 1, 1, list(body.ljust(251, b"\0"))))
        nak = gcs.recv(2.0, "FILE_TRANSFER_PROTOCOL")
        assert nak.payload[3] == ftp_wire.OP_NAK and nak.payload[0] == 6
        gcs.send(mavlink.MAVLink_mission_request_list_message(1, 1, 0))
        assert gcs.recv(2.0, "MISSION_COUNT").count == 0


def test_restart_a_thread_and_logging_commands() -> None:
    calls: list[bool] = []

    def logging_control(start: bool) -> str | None:
        calls.append(start)
        return None

    with running(logging_control=logging_control) as (v, gcs):
        imu = v.manager.find(1)
        assert imu is not None
        assert command(gcs, CMD_RESTART_THREAD, 1).result == 0
        assert imu.restarts == 1  # ACCEPTED means done
        # a retransmission (the ACK was lost, confirmation > 0) is acknowledged, not redone
        gcs.send(mavlink.MAVLink_command_long_message(1, 1, CMD_RESTART_THREAD, 1, 1, *[NAN] * 6))
        assert gcs.recv(3.0, "COMMAND_ACK").result == 0
        assert imu.restarts == 1
        gcs.send(mavlink.MAVLink_command_long_message(1, 1, CMD_RESTART_THREAD, 0, 77, *[NAN] * 6))
        assert "no thread 77" in gcs.seen(2.0, "STATUSTEXT", lambda m: "77" in m.text).text
        assert gcs.recv(2.0, "COMMAND_ACK").result == mavlink.MAV_RESULT_DENIED
        assert command(gcs, CMD_RESTART_THREAD).result == mavlink.MAV_RESULT_DENIED  # NaN id
        # the watchdog's news reach the ground as STATUSTEXT
        text = gcs.seen(2.0, "STATUSTEXT", lambda m: m.text.startswith("imu: restarted"))
        assert text is not None and text.severity == mavlink.MAV_SEVERITY_NOTICE
        assert command(gcs, mavlink.MAV_CMD_LOGGING_STOP).result == 0
        assert command(gcs, mavlink.MAV_CMD_LOGGING_START, 0, use_int=True).result == 0
        assert calls == [False, True]


@pytest.mark.parametrize("param1,reason", [(1, "reboot"), (2, "stop")])
def test_reboot_and_shutdown_stop_the_runtime_after_the_ack(param1: int, reason: str) -> None:
    gcs = MiniGcs(listen_port=free_udp_port())
    v = SyntheticVehicle([f"udpout:127.0.0.1:{gcs.port}"])
    try:
        v.start()
        assert gcs.recv(5.0, "HEARTBEAT") is not None
        assert command(gcs, mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 0).result == 0  # no-op
        assert v.run_reason is None
        ack = command(gcs, mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, param1)
        assert ack is not None and ack.result == 0
        assert v.wait_stopped(5.0) and v.run_reason == reason
    finally:
        v.stop()
        gcs.close()


def test_bootloader_reboot_is_unsupported() -> None:
    with running() as (v, gcs):
        assert command(gcs, mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 3).result == \
            mavlink.MAV_RESULT_UNSUPPORTED
        assert v.run_reason is None
