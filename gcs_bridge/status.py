"""Identity and health messages: HEARTBEAT, SYS_STATUS, thread status, STATUSTEXT, versions.

Health comes from the thread manager (the software watchdog): a thread is healthy when it is
enabled, initialised, running, in its periodic section and was alive at the last watchdog
check (the thesis's four LEDs), and has not been given up.
"""

from __future__ import annotations

from dataclasses import dataclass

from companion import __version__
from companion.core.state import ServoState
from companion.watchdog import ThreadStatus
from gcs_bridge.dialect import UINT16_MAX, Identity, ProtocolVersionMessage, clamp_int, mavlink
from gcs_bridge.dialect import Message as Msg
from gcs_bridge.runtime_view import (
    BridgeCore,
)
from gcs_bridge.telemetry import battery_percent

STATUSTEXT_LEN = 50
MAX_STATUSTEXT_CHUNKS = 4

# Custom modes for "pilot flies" and "the computer's control law flies", per identity.
_PX4_MANUAL = 1 << 16
_PX4_STABILIZED = 7 << 16
_APM_PLANE_MANUAL = 0
_APM_PLANE_STABILIZE = 2

# a slot a thread publishes (its row's `publishes`) -> the MAV_SYS_STATUS_SENSOR bits it stands
# for: a thread is known by what it produces, so this module keeps no list of thread ids
_SENSOR_BITS = {
    "imu": mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL,
    "gps": mavlink.MAV_SYS_STATUS_SENSOR_GPS,
    "servo": mavlink.MAV_SYS_STATUS_SENSOR_RC_RECEIVER | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS,
    "estimator": mavlink.MAV_SYS_STATUS_AHRS,
    "control": mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL,
}


def _bits_of(publishes: tuple[str, ...]) -> int:
    bits = 0
    for slot in publishes:
        bits |= _SENSOR_BITS.get(slot, 0)
    return bits


@dataclass
class LinkCounters:
    """Per-link figures that SYS_STATUS and the link's named values report."""

    rx_frames: int = 0
    tx_frames: int = 0
    parse_errors: int = 0
    refused: int = 0  # signing policy refusals (never acted on)
    queue_dropped: int = 0
    stale_skips: int = 0  # stream slots skipped because no fresh data arrived


def thread_healthy(st: ThreadStatus) -> bool:
    return (st.enabled and st.initialised and st.running and st.in_periodic and st.alive
            and not st.failed)


def led_bits(st: ThreadStatus) -> int:
    """The legacy THREAD_STATUS flags (bit0 initialised .. bit3 alive), bit4 failed."""
    return (int(st.initialised) | int(st.running) << 1 | int(st.in_periodic) << 2
            | int(st.alive) << 3 | int(st.failed) << 4)


def autonomous(core: BridgeCore) -> bool:
    """Whether the computer's control law is flying (pilot switch engaged and law enabled)."""
    servo = core.ctx.state.servo.read()
    control = core.ctx.state.control.read()
    return bool(servo is not None and servo.auto_engaged and control is not None and control.enabled)


def system_state(core: BridgeCore) -> int:
    ms = core.manager.status()
    if ms.stopping:
        return int(mavlink.MAV_STATE_POWEROFF)
    statuses = core.manager.thread_status()
    # until every thread has had its first watchdog check (due one period after its start,
    # later on a busy machine), "not alive yet" is not a fault
    first_check_ms = 2 * max((st.watchdog_ms for st in statuses), default=0) + ms.granularity_ms
    if ms.elapsed_ms < first_check_ms:
        return int(mavlink.MAV_STATE_BOOT)
    if any(st.failed for st in statuses):
        return int(mavlink.MAV_STATE_EMERGENCY)
    if not ms.healthy:
        return int(mavlink.MAV_STATE_CRITICAL)
    if autonomous(core):
        return int(mavlink.MAV_STATE_ACTIVE)
    return int(mavlink.MAV_STATE_STANDBY)


def heartbeat(core: BridgeCore, identity: Identity = Identity.GENERIC) -> Msg:
    """The link's HEARTBEAT: the mode is said in the base mode's flags, which every client
    reads; a PX4 or ArduPilot claim adds that firmware's custom mode number for the same mode,
    since their plugins name the mode from it. Beside an autopilot it is a companion's:
    `MAV_TYPE_ONBOARD_CONTROLLER`, `MAV_AUTOPILOT_INVALID`, no mode (the autopilot has the
    vehicle's), so no client takes it for the vehicle."""
    if core.beside_autopilot:
        return mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
            system_state(core), 3)
    auto = autonomous(core)
    base = mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
    if auto:
        base |= mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
    custom = 0
    if identity is Identity.PX4:
        base |= mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        custom = _PX4_STABILIZED if auto else _PX4_MANUAL
    elif identity is Identity.ARDUPILOT:
        base |= mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        custom = _APM_PLANE_STABILIZE if auto else _APM_PLANE_MANUAL
    return mavlink.MAVLink_heartbeat_message(
        mavlink.MAV_TYPE_FIXED_WING, identity.autopilot, base, custom, system_state(core), 3)


def system_time(core: BridgeCore) -> Msg:
    return mavlink.MAVLink_system_time_message(core.time_usec(), core.time_boot_ms())


def sensor_bits(core: BridgeCore) -> tuple[int, int, int]:
    """(present, enabled, healthy) MAV_SYS_STATUS_SENSOR bitmaps from the threads."""
    present = enabled = healthy = 0
    state = core.ctx.state
    servo_thread = False
    for thread, st in zip(core.manager.threads, core.manager.thread_status(), strict=True):
        publishes = thread.task.publishes
        servo_thread = servo_thread or "servo" in publishes
        bits = _bits_of(publishes)
        if not bits:
            continue
        present |= bits
        if st.enabled:
            enabled |= bits
        if not thread_healthy(st):
            continue
        ok = bits
        if "imu" in publishes:
            imu = state.imu.read()
            if imu is not None:
                if not imu.gyro_ok:
                    ok &= ~mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
                if not imu.accel_ok:
                    ok &= ~mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
        if "servo" in publishes:
            servo = state.servo.read()
            if servo is not None and servo.failsafe:
                ok &= ~mavlink.MAV_SYS_STATUS_SENSOR_RC_RECEIVER
        if "estimator" in publishes:
            est = state.estimator.read()
            if est is None or not est.aligned or est.faults:
                ok &= ~mavlink.MAV_SYS_STATUS_AHRS
        healthy |= ok
    servo = state.servo.read()
    if servo_thread:
        batt = mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
        present |= batt
        enabled |= batt
        if servo is not None and _batteries_ok(core, servo):
            healthy |= batt
    # No geofence exists: not present, not enabled, and nothing breached. MAVProxy's fence
    # module reads a clear health bit as a breach (and says "fence breach" on connecting).
    healthy |= mavlink.MAV_SYS_STATUS_GEOFENCE
    if core.ctx.logs is not None:
        present |= mavlink.MAV_SYS_STATUS_LOGGING
        enabled |= mavlink.MAV_SYS_STATUS_LOGGING
        healthy |= mavlink.MAV_SYS_STATUS_LOGGING
    return present, enabled, healthy


def _batteries_ok(core: BridgeCore, servo: ServoState) -> bool:
    p = core.ctx.params
    raw_empty = int(p.get("MAV_B_RAW_EMPTY"))
    low = int(p.get("MAV_B_LOW_PCT"))
    return all(battery_percent(raw, raw_empty) >= low
               for raw in (servo.avionics_batt_raw, servo.servo_batt_raw))


def sys_status(core: BridgeCore, link: LinkCounters) -> Msg:
    present, enabled, healthy = sensor_bits(core)
    servo = core.ctx.state.servo.read()
    if servo is not None:
        p = core.ctx.params
        mv = clamp_int(servo.avionics_batt_raw / 100.0 * float(p.get("MAV_B1_V_FULL")) * 1000,
                       0, UINT16_MAX - 1, UINT16_MAX)
        pct = battery_percent(servo.avionics_batt_raw, int(p.get("MAV_B_RAW_EMPTY")))
    else:
        mv, pct = UINT16_MAX, -1
    statuses = core.manager.thread_status()
    restarts = sum(st.restarts for st in statuses)
    stalls = sum(st.stalls for st in statuses)
    total = link.rx_frames + link.parse_errors
    drop_cpct = clamp_int(10000.0 * link.parse_errors / total if total else 0, 0, 10000, 0)
    return mavlink.MAVLink_sys_status_message(
        present, enabled, healthy, core.cpu_load_permille(), mv, -1, pct, drop_cpct,
        clamp_int(link.parse_errors, 0, UINT16_MAX, 0),
        clamp_int(link.refused, 0, UINT16_MAX, 0),  # errors_count1: refused (signing)
        clamp_int(restarts, 0, UINT16_MAX, 0),  # errors_count2: thread restarts
        clamp_int(stalls, 0, UINT16_MAX, 0),  # errors_count3: stalls seen by the watchdog
        clamp_int(link.queue_dropped, 0, UINT16_MAX, 0),  # errors_count4: replies dropped
        0, 0, 0)


def _named_int(t_ms: int, name: str, value: int) -> Msg:
    return mavlink.MAVLink_named_value_int_message(
        t_ms, name[:10].encode("ascii"), clamp_int(value, -(2**31), 2**31 - 1, 0))


def thread_status_messages(core: BridgeCore, st: ThreadStatus) -> list[Msg]:
    """One thread's status as named values a stock GCS shows, names `T<id>_<FIELD>` (<= 10)."""
    if not 0 <= st.thread_id < 100:
        return []
    t_ms = core.time_boot_ms()
    p = f"T{st.thread_id}_"
    return [
        _named_int(t_ms, p + "LEDS", led_bits(st)),
        _named_int(t_ms, p + "RST", st.restarts),
        mavlink.MAVLink_named_value_float_message(t_ms, (p + "STEPUS").encode("ascii"),
                                                  float(st.mean_step_us)),
        _named_int(t_ms, p + "WDGMS", st.watchdog_ms),
        _named_int(t_ms, p + "MSGMS", st.message_ms),
    ]


def link_messages(core: BridgeCore, index: int, link: LinkCounters) -> list[Msg]:
    t_ms = core.time_boot_ms()
    p = f"L{index}_"
    return [
        _named_int(t_ms, p + "RX", link.rx_frames),
        _named_int(t_ms, p + "TX", link.tx_frames),
        _named_int(t_ms, p + "REFUSED", link.refused),
        _named_int(t_ms, p + "DROPPED", link.queue_dropped),
    ]


class StatusTextIds:
    """Chunk ids for multi-part STATUSTEXT (shared by all links so ids stay unique)."""

    def __init__(self) -> None:
        self._next = 0

    def next(self) -> int:
        self._next = self._next % 65535 + 1
        return self._next


def statustext(severity: int, text: str, ids: StatusTextIds | None = None) -> list[Msg]:
    """STATUSTEXT for `text`: one message up to 50 bytes, else up to 4 chunks (MAVLink 2)."""
    data = text.encode("utf-8", errors="replace")[: STATUSTEXT_LEN * MAX_STATUSTEXT_CHUNKS]
    if len(data) <= STATUSTEXT_LEN or ids is None:
        return [mavlink.MAVLink_statustext_message(severity, data[:STATUSTEXT_LEN], 0, 0)]
    chunk_id = ids.next()
    parts = [data[i:i + STATUSTEXT_LEN] for i in range(0, len(data), STATUSTEXT_LEN)]
    if len(parts[-1]) == STATUSTEXT_LEN and len(parts) < MAX_STATUSTEXT_CHUNKS:
        parts.append(b"")  # a text filling its last chunk needs an empty one to end it
    return [mavlink.MAVLink_statustext_message(severity, part, chunk_id, seq)
            for seq, part in enumerate(parts)]


def _version_word() -> int:
    parts = [int(p) if p.isdigit() else 0 for p in __version__.split(".")[:3]]
    parts += [0] * (3 - len(parts))
    return (parts[0] & 0xFF) << 24 | (parts[1] & 0xFF) << 16 | (parts[2] & 0xFF) << 8 | \
        mavlink.FIRMWARE_VERSION_TYPE_DEV


def autopilot_version(core: BridgeCore, identity: Identity = Identity.GENERIC) -> Msg:
    caps = (mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
            | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT | mavlink.MAV_PROTOCOL_CAPABILITY_FTP)
    caps |= (mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE if identity.bytewise
             else mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST)
    return mavlink.MAVLink_autopilot_version_message(
        caps, _version_word(), 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, core.sysid, [0] * 18)


def protocol_version() -> Msg:
    return ProtocolVersionMessage(200, 100, 200)
