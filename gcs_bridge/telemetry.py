"""State slots to MAVLink telemetry: the only place SI units become MAVLink's scaled integers.

Each builder reads one snapshot (frozen dataclasses from `companion.core.state`) and returns the
messages for it, or nothing when the data is not there yet. Missing values become the field's
"unknown" marker (UINT16_MAX, NaN, ...) rather than a plausible-looking zero.
"""

from __future__ import annotations

import math
from functools import lru_cache

from companion.core.geo import NedFrame
from companion.core.state import EstimatorState, GpsFix, ImuSample, ImuSlowSample, ServoState
from gcs_bridge.dialect import INT16_MAX, UINT16_MAX, clamp_int, mavlink, nan_if_none
from gcs_bridge.dialect import Message as Msg
from gcs_bridge.runtime_view import BridgeCore

G0_M_S2 = 9.80665
INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1

# our fix code (0 none, 1 GPS, 2 DGPS, 3 RTK) -> GPS_FIX_TYPE
_FIX_TYPE = {
    1: mavlink.GPS_FIX_TYPE_3D_FIX,
    2: mavlink.GPS_FIX_TYPE_DGPS,
    3: mavlink.GPS_FIX_TYPE_RTK_FIXED,
}


def _deg_e7(deg: float | None) -> int:
    return clamp_int(None if deg is None else deg * 1e7, INT32_MIN, INT32_MAX, 0)


def _mm(m: float | None) -> int:
    return clamp_int(None if m is None else m * 1000.0, INT32_MIN, INT32_MAX, 0)


def _cdeg_heading(deg: float | None) -> int:
    if deg is None or not math.isfinite(deg):
        return UINT16_MAX
    return int(round((deg % 360.0) * 100.0)) % 36000


@lru_cache(maxsize=8)
def _frame(lat_deg: float, lon_deg: float, alt_m: float) -> NedFrame:
    return NedFrame(lat_deg, lon_deg, alt_m)


def geodetic_of(est: EstimatorState) -> tuple[float, float, float] | None:
    """Latitude, longitude (deg) and altitude MSL (m) of the estimate, None without an origin."""
    if est.origin_lat_deg is None or est.origin_lon_deg is None:
        return None
    alt0 = est.origin_alt_m if est.origin_alt_m is not None else 0.0
    n, e, d = est.pos_ned_m
    if not all(math.isfinite(v) for v in (n, e, d)):
        return None
    try:
        lat, lon, alt = _frame(est.origin_lat_deg, est.origin_lon_deg, alt0).to_geodetic(n, e, d)
    except ValueError:
        return None
    return lat, lon, alt


# ------------------------------------------------------------------------------- estimator
def attitude(core: BridgeCore, est: EstimatorState) -> list[Msg]:
    p, q, r = est.rates_rad_s
    return [mavlink.MAVLink_attitude_message(
        core.time_boot_ms(est.t_ns), est.roll_rad, est.pitch_rad, est.yaw_rad, p, q, r)]


def attitude_quaternion(core: BridgeCore, est: EstimatorState) -> list[Msg]:
    w, x, y, z = est.quat_wxyz
    p, q, r = est.rates_rad_s
    return [mavlink.MAVLink_attitude_quaternion_message(
        core.time_boot_ms(est.t_ns), w, x, y, z, p, q, r, [0.0, 0.0, 0.0, 0.0])]


def local_position_ned(core: BridgeCore, est: EstimatorState) -> list[Msg]:
    n, e, d = est.pos_ned_m
    vn, ve, vd = est.vel_ned_m_s
    return [mavlink.MAVLink_local_position_ned_message(
        core.time_boot_ms(est.t_ns), n, e, d, vn, ve, vd)]


def global_position_int(core: BridgeCore, est: EstimatorState) -> list[Msg]:
    geo = geodetic_of(est)
    if geo is None:
        return []
    lat, lon, alt = geo
    vn, ve, vd = est.vel_ned_m_s
    return [mavlink.MAVLink_global_position_int_message(
        core.time_boot_ms(est.t_ns), _deg_e7(lat), _deg_e7(lon), _mm(alt),
        _mm(-est.pos_ned_m[2]),
        clamp_int(vn * 100, -32768, 32767, 0), clamp_int(ve * 100, -32768, 32767, 0),
        clamp_int(vd * 100, -32768, 32767, 0), _cdeg_heading(math.degrees(est.yaw_rad)))]


def vfr_hud(core: BridgeCore, est: EstimatorState, throttle: float | None) -> list[Msg]:
    vn, ve, vd = est.vel_ned_m_s
    ground_m_s = math.hypot(vn, ve)
    geo = geodetic_of(est)
    alt = geo[2] if geo is not None else -est.pos_ned_m[2]
    heading = clamp_int(math.degrees(est.yaw_rad) % 360.0, 0, 359, 0)
    throttle_pct = clamp_int(None if throttle is None else throttle * 100.0, 0, 100, 0)
    # no air-data sensor: airspeed is reported as ground speed, as GCSs expect a number
    return [mavlink.MAVLink_vfr_hud_message(ground_m_s, ground_m_s, heading, throttle_pct,
                                            alt, -vd)]


LANDED_SPEED_M_S = 5.0
"""Ground speed above which a fixed wing is taken to be in the air: far below any aircraft's
stall speed, far above a GPS/INS velocity's noise at rest. (No weight-on-wheels switch exists.)"""


def extended_sys_state(core: BridgeCore, est: EstimatorState | None) -> list[Msg]:
    """EXTENDED_SYS_STATE: QGroundControl takes the landed state from it (not from VFR_HUD)."""
    if est is None or not est.aligned:
        landed = mavlink.MAV_LANDED_STATE_UNDEFINED
    else:
        vn, ve, _vd = est.vel_ned_m_s
        landed = (mavlink.MAV_LANDED_STATE_IN_AIR if math.hypot(vn, ve) > LANDED_SPEED_M_S
                  else mavlink.MAV_LANDED_STATE_ON_GROUND)
    return [mavlink.MAVLink_extended_sys_state_message(mavlink.MAV_VTOL_STATE_UNDEFINED, landed)]


def home_of(core: BridgeCore) -> tuple[float, float, float] | None:
    """Home (lat, lon deg, alt MSL m): the estimator's NED origin, else the configured one."""
    est = core.ctx.state.estimator.read()
    if est is not None and est.origin_lat_deg is not None and est.origin_lon_deg is not None:
        return est.origin_lat_deg, est.origin_lon_deg, est.origin_alt_m or 0.0
    configured = getattr(core.ctx, "home_lla", None)
    if configured is not None:
        lat, lon, alt = configured
        return float(lat), float(lon), float(alt)
    return None


def home_position(core: BridgeCore, _value: object = None) -> list[Msg]:
    home = home_of(core)
    if home is None:
        return []
    lat, lon, alt = home
    return [mavlink.MAVLink_home_position_message(
        _deg_e7(lat), _deg_e7(lon), _mm(alt), 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0,
        core.time_usec())]


# ------------------------------------------------------------------------------- GPS
def _gps_yaw_cdeg(core: BridgeCore, heading_deg: float | None) -> int:
    """GPS_RAW_INT.yaw: a dual-antenna receiver's heading turned into the airframe's by the
    baseline's yaw on it (EST_HDG_OFS); 0 says "no yaw", so north is 36000."""
    if heading_deg is None or not math.isfinite(heading_deg):
        return 0
    params = core.ctx.params
    offset_deg = math.degrees(float(params.get("EST_HDG_OFS"))) if "EST_HDG_OFS" in params else 0.0
    return int(round(((heading_deg - offset_deg) % 360.0) * 100.0)) % 36000 or 36000


def gps_raw_int(core: BridgeCore, fix: GpsFix) -> list[Msg]:
    if fix.lat_deg is None or fix.lon_deg is None:
        fix_type = mavlink.GPS_FIX_TYPE_NO_FIX
    else:
        fix_type = _FIX_TYPE.get(fix.fix, mavlink.GPS_FIX_TYPE_NO_FIX)
        if fix_type == mavlink.GPS_FIX_TYPE_3D_FIX and fix.alt_m is None:
            fix_type = mavlink.GPS_FIX_TYPE_2D_FIX
    msgs: list[Msg] = [mavlink.MAVLink_gps_raw_int_message(
        core.time_usec(fix.t_ns), fix_type, _deg_e7(fix.lat_deg), _deg_e7(fix.lon_deg),
        _mm(fix.alt_m),
        clamp_int(None if fix.hdop is None else fix.hdop * 100, 0, UINT16_MAX - 1, UINT16_MAX),
        clamp_int(None if fix.vdop is None else fix.vdop * 100, 0, UINT16_MAX - 1, UINT16_MAX),
        clamp_int(None if fix.speed_m_s is None else fix.speed_m_s * 100, 0, UINT16_MAX - 1,
                  UINT16_MAX),
        _cdeg_heading(fix.course_deg),
        clamp_int(fix.sats, 0, 254, 255),
        0,
        clamp_int(None if fix.h_std_m is None else fix.h_std_m * 1000, 0, 2**32 - 1, 0),
        clamp_int(None if fix.alt_std_m is None else fix.alt_std_m * 1000, 0, 2**32 - 1, 0),
        0, 0, _gps_yaw_cdeg(core, fix.heading_deg))]
    # PDOP and TDOP have no field in GPS_RAW_INT; every GCS can plot named values
    for name, value in (("GPS_PDOP", fix.pdop), ("GPS_TDOP", fix.tdop)):
        if value is not None and math.isfinite(value):
            msgs.append(mavlink.MAVLink_named_value_float_message(
                core.time_boot_ms(fix.t_ns), name.encode("ascii"), float(value)))
    return msgs


# ------------------------------------------------------------------------------- IMU
_HIGHRES_ACC_GYRO = 0x3F  # fields_updated bits 0..5
_HIGHRES_TEMP = 1 << 12


def highres_imu(core: BridgeCore, imu: ImuSample, slow: ImuSlowSample | None) -> list[Msg]:
    ax, ay, az = imu.accel_m_s2
    p, q, r = imu.rates_rad_s
    temp = slow.temperature_c if slow is not None else None
    nan = float("nan")
    fields = _HIGHRES_ACC_GYRO | (_HIGHRES_TEMP if temp is not None else 0)
    return [mavlink.MAVLink_highres_imu_message(
        core.time_usec(imu.t_ns), ax, ay, az, p, q, r, nan, nan, nan, nan, nan, nan,
        nan_if_none(temp), fields, 0)]


def scaled_imu(core: BridgeCore, imu: ImuSample, slow: ImuSlowSample | None) -> list[Msg]:
    ax, ay, az = imu.accel_m_s2
    p, q, r = imu.rates_rad_s

    def mg(a: float) -> int:
        return clamp_int(a / G0_M_S2 * 1000.0, -32768, 32767, 0)

    def mrad(w: float) -> int:
        return clamp_int(w * 1000.0, -32768, 32767, 0)

    temp_cdeg = 0  # 0 means "no temperature", so a real 0 degC is sent as 0.01 degC
    if slow is not None:
        temp_cdeg = clamp_int(slow.temperature_c * 100, -32767, 32767, 0) or 1
    return [mavlink.MAVLink_scaled_imu_message(
        core.time_boot_ms(imu.t_ns), mg(ax), mg(ay), mg(az), mrad(p), mrad(q), mrad(r),
        0, 0, 0, temp_cdeg)]


# ------------------------------------------------------------------------------- servo board
def _channels(values: tuple[int, ...], n: int, missing: int) -> list[int]:
    out = [clamp_int(v, 0, UINT16_MAX - 1, missing) for v in values[:n]]
    return out + [missing] * (n - len(out))


def rc_channels(core: BridgeCore, servo: ServoState) -> list[Msg]:
    ch = _channels(servo.pilot_us, 18, UINT16_MAX)
    rssi = 0 if servo.failsafe else 255  # 255: unknown; a failsafe means no radio at all
    return [mavlink.MAVLink_rc_channels_message(
        core.time_boot_ms(servo.t_ns), min(len(servo.pilot_us), 18), *ch, rssi)]


def servo_output_raw(core: BridgeCore, servo: ServoState) -> list[Msg]:
    ch = _channels(servo.computer_us, 16, 0)
    t_us = ((servo.t_ns - core.boot_real_ns) // 1000) & 0xFFFFFFFF
    return [mavlink.MAVLink_servo_output_raw_message(t_us, 0, *ch)]


def battery_percent(raw: int, raw_empty: int) -> int:
    """Remaining charge from the board's raw reading (100 = full, `raw_empty` = 0 %)."""
    span = max(1, 100 - raw_empty)
    return clamp_int((raw - raw_empty) * 100.0 / span, 0, 100, -1)


def battery_status(core: BridgeCore, servo: ServoState) -> list[Msg]:
    p = core.ctx.params
    raw_empty = int(p.get("MAV_B_RAW_EMPTY"))
    low = int(p.get("MAV_B_LOW_PCT"))
    msgs: list[Msg] = []
    batteries = (
        (0, servo.avionics_batt_raw, float(p.get("MAV_B1_V_FULL")),
         mavlink.MAV_BATTERY_FUNCTION_AVIONICS),
        # the servo pack drives actuators: no MAV_BATTERY_FUNCTION says that
        (1, servo.servo_batt_raw, float(p.get("MAV_B2_V_FULL")), mavlink.MAV_BATTERY_FUNCTION_UNKNOWN),
    )
    for ident, raw, v_full, function in batteries:
        pct = battery_percent(raw, raw_empty)
        mv = clamp_int(raw / 100.0 * v_full * 1000.0, 0, UINT16_MAX - 1, UINT16_MAX)
        state = (mavlink.MAV_BATTERY_CHARGE_STATE_OK if pct >= low else
                 mavlink.MAV_BATTERY_CHARGE_STATE_LOW if pct > low // 2 else
                 mavlink.MAV_BATTERY_CHARGE_STATE_CRITICAL)
        msgs.append(mavlink.MAVLink_battery_status_message(
            ident, function, mavlink.MAV_BATTERY_TYPE_NIMH, INT16_MAX,
            [mv] + [UINT16_MAX] * 9, -1, -1, -1, pct, 0, state, [0, 0, 0, 0], 0, 0))
    return msgs
