"""The link to the flight controller: one supervised thread, the source of the autopilot's data.

A row of the vehicle's table (``autopilot``, `companion/vehicle.py`) configured as
``[devices.autopilot] port = URL`` or ``companion run --autopilot URL``, where URL is a
pymavlink connection string (``/dev/serial0,921600``, ``tcp:127.0.0.1:5760``,
``udpin:0.0.0.0:14550``, ``udpout:...``). The thread:

* learns the autopilot's system and component id and its firmware (ArduPilot, PX4) from its
  HEARTBEAT, and only takes data from that component (a changed system id, or a second
  autopilot, is reported, not mixed in);
* asks for the messages it needs with SET_MESSAGE_INTERVAL (the autopilot's stream settings,
  ArduPilot's ``SRn_*``, are never written), asks again while one has not come, and says in
  its counters what each message's rate is;
* maps the autopilot's clock onto the runtime's (`ClockSync`: TIMESYNC round trips, the
  offset, drift and latency logged), so a sample's time is when it was measured;
* publishes the IMU, GPS, RC and outputs into the slots the thesis devices fill (``imu``,
  ``imu_stream``, ``gps``, ``servo``) and writes the same logs they write (``imu.bin``,
  ``gps.bin``, ``servo.bin``: the estimator, the report and the converters work unchanged), the
  autopilot's own estimate into the ``autopilot`` slot and ``autopilot.bin``, and a SITL's
  SIMSTATE into ``truth.bin``;
* hands every frame, as received, to the ``autopilot_rx`` queue (the router's input) and sends
  what the bridges put on ``autopilot_tx``: the thread neither routes nor answers the ground.

Nothing the link receives can stop it: a frame that fails its checksum is counted, a message
that is not the autopilot's is forwarded but not used (frames are cut by
`gcs_bridge.framing`, which finds its way back after damage byte by byte), and silence is the watchdog's SILENT
event (the transport reopens a vanished port by itself).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from typing import Any, Self

from pymavlink.dialects.v20 import ardupilotmega as apm

from companion.core.config import DeviceConfig
from companion.core.params import ParamSpec
from companion.core.state import ImuSlowSample
from companion.drivers.gps import FIX_LAYOUT, FMT_SOLUTION, define_fix_log
from companion.drivers.imu import FMT_FAST, FMT_SLOW, define_sample_logs
from companion.drivers.servo import FMT_EXCHANGE, define_exchange_log
from companion.logs.truth import FMT_TRUTH, define_truth_log
from companion.watchdog.task import Task
from companion.watchdog.thread import ManagedThread
from gcs_bridge.autopilot.params import link_params
from gcs_bridge.autopilot.samples import (
    IMU_MESSAGES,
    AutopilotEstimate,
    BatterySample,
    Firmware,
    euler_from_quat,
    gps_fix,
    imu_sample,
    imu_temperature_c,
    message_time_ns,
    quat_from_euler_wxyz,
    servo_state,
    truth_sample,
)
from gcs_bridge.autopilot.streams import REQUEST_EVERY_S, StreamRequests
from gcs_bridge.autopilot.timesync import ClockSync
from gcs_bridge.framing import Frame, FrameSplitter, decoder
from gcs_bridge.transports.base import Transport, make_transport
from gcs_bridge.transports.endpoints import parse_endpoint

log = logging.getLogger(__name__)

__all__ = ["AutopilotLink", "COMPANION_COMPONENT", "RX_QUEUE", "TX_QUEUE"]

COMPANION_COMPONENT = apm.MAV_COMP_ID_ONBOARD_COMPUTER  # 191
RX_QUEUE = "autopilot_rx"
"""Frames from the autopilot, as received: ``(src_system, src_component, msg_id, bytes)``."""
TX_QUEUE = "autopilot_tx"
"""Frames for the autopilot, as bytes, put there by the bridges (router, control)."""

FMT_TSYNC = 1
FMT_ESTIMATE = 2
FMT_HEARTBEAT = 3
FMT_RATES = 4
FMT_COMMAND = 5

CONTROL_FRESH_S = 0.1
"""A control output older than this is not sent: the autopilot's own timeout takes over."""
_IGNORE_BODY_RATES = 0b00000111  # SET_ATTITUDE_TARGET type_mask: fly the attitude, not rates

RECV_TIMEOUT_S = 0.05
_ARDUPLANE_GUIDED = 15
_PX4_OFFBOARD = 6 << 16

_USED = frozenset(apm.mavlink_map[getattr(apm, f"MAVLINK_MSG_ID_{name}")].id for name in (
    "HEARTBEAT", *IMU_MESSAGES, "GPS_RAW_INT", "GPS2_RAW", "ATTITUDE", "ATTITUDE_QUATERNION",
    "GLOBAL_POSITION_INT", "EKF_STATUS_REPORT", "RC_CHANNELS", "SERVO_OUTPUT_RAW", "SIMSTATE",
    "SYSTEM_TIME", "TIMESYNC", "COMMAND_ACK", "BATTERY_STATUS"))
"""The messages the link reads; every other frame is only handed to the router."""


@dataclasses.dataclass(frozen=True)
class AutopilotIdentity:
    """Who is on the other end, from its HEARTBEAT."""

    system: int
    component: int
    firmware: str
    vehicle_type: int


class AutopilotLink(ManagedThread):
    """Reads the autopilot's frames, publishes its data, keeps its streams and clock."""

    def __init__(self, url: str, baudrate: int = 921600, *, task: Task) -> None:
        super().__init__(task)
        endpoint = parse_endpoint(url)  # a bad URL is a ConfigError naming it, at build time
        if endpoint.kind == "serial" and "," not in url.partition("?")[0]:
            endpoint = dataclasses.replace(endpoint, baud=baudrate)
        self.url = url
        self.endpoint = endpoint
        self.transport: Transport | None = None
        self.sync = ClockSync()
        self.identity: AutopilotIdentity | None = None
        self.guided = False
        self._splitter = FrameSplitter()
        self._decoder = decoder()
        self._out = apm.MAVLink(None, srcSystem=1, srcComponent=COMPANION_COMPONENT)
        self._imu_kind: str | None = None
        self._imu_counter = 0
        self._rc: Any = None
        self._outputs: Any = None
        self._servo_seq = 0
        self._estimate: dict[str, Any] = {}
        self._pending_sync: dict[int, int] = {}
        self._next_heartbeat_ns = 0
        self._next_sync_ns = 0
        self._next_request_ns = 0
        self.streams = StreamRequests()
        self._logs: dict[str, Any] = {}
        self._logs_begun = False
        self._last_heartbeat_ns = 0
        self.c: dict[str, int] = dict.fromkeys((
            "frames", "bad_frames", "undecodable", "bytes_in", "frames_out", "tx_failed", "heartbeats",
            "foreign_frames", "system_changes", "reboots", "requests", "acks_refused",
            "imu_samples", "gps_fixes", "estimates", "truth_samples", "time_syncs",
            "attitude_targets", "offboard_prestream"), 0)
        self._next_command_ns = 0
        self._unix_minus_boot_ns: int | None = None
        self._last_stamp_ns = 0
        self._attitude_kind: str | None = None

    @classmethod
    def from_row(cls, task: Task, settings: DeviceConfig | None) -> Self:
        if settings is None or not settings.port:
            raise ValueError(f"{task.name}: no autopilot URL configured "
                             "([devices.autopilot] port, or --autopilot URL)")
        return cls(settings.port, settings.baud, task=task)

    @classmethod
    def declare_params(cls, prefix: str) -> list[ParamSpec]:
        return link_params(prefix)

    # ------------------------------------------------------------------ logs
    def define_logs(self, tlog: Any) -> None:
        tlog.define(FMT_TSYNC, "%.3lf,%.3f,%.3f,%.3f,%hhu,%hu",
                    ["offset_ms", "drift_ppm", "latency_ms", "rtt_ms", "synced", "resets"])
        tlog.define(FMT_ESTIMATE, ",".join(["%.6f"] * 6 + ["%.9lf", "%.9lf"] + ["%.3f"] * 4)
                    + ",%hu",
                    ["roll_rad", "pitch_rad", "yaw_rad", "p_rad_s", "q_rad_s", "r_rad_s",
                     "lat_deg", "lon_deg", "alt_m", "vn_m_s", "ve_m_s", "vd_m_s", "ekf_flags"])
        tlog.define(FMT_HEARTBEAT, "%hhu,%hhu,%hhu,%hhu,%hhu,%u,%hhu",
                    ["system", "component", "autopilot", "type", "base_mode", "custom_mode",
                     "system_status"])
        tlog.define(FMT_RATES, "%u,%.2f", ["msg_id", "rate_hz"])
        tlog.define(FMT_COMMAND, "%.4f,%.4f,%.4f,%.3f,%hhu",
                    ["roll_sp_rad", "pitch_sp_rad", "yaw_sp_rad", "thrust", "guided"])

    def open_log(self) -> None:
        """Its own log, and the logs of the slots it fills, each in the layout of the thesis
        device that fills it elsewhere (``imu.bin`` ...), or ``autopilot_<slot>.bin`` when that
        device runs too."""
        super().open_log()
        logs = self.ctx.logs
        if logs is None or self._logs:
            return
        for name, define in (("imu", define_sample_logs), ("gps", define_fix_log),
                             ("servo", define_exchange_log), ("truth", define_truth_log)):
            try:
                tlog = logs.open(name)
            except ValueError:
                tlog = logs.open(f"autopilot_{name}")
            define(tlog)
            self._logs[name] = tlog

    # ------------------------------------------------------------------ lifecycle
    def setup(self) -> None:
        self.transport = make_transport(self.endpoint)
        self.transport.open()

    def cleanup(self) -> None:
        self._end_logs()
        transport, self.transport = self.transport, None
        if transport is not None:
            transport.close()

    def interrupt_io(self) -> None:
        if self.transport is not None:
            self.transport.wake()

    def recover(self) -> None:
        self._splitter.reset()

    def prologue(self) -> bool:
        for tlog in self._logs.values():
            tlog.begin()
        self._logs_begun = True
        return True

    def _end_logs(self) -> None:
        if self._logs_begun:
            self._logs_begun = False
            for tlog in self._logs.values():
                tlog.end()

    def io_bytes(self) -> int:
        return self.c["bytes_in"]

    def counters(self) -> dict[str, int]:
        out = dict(self.c)
        est = self.sync.estimate()
        out["clock_offset_ms"] = int(est.offset_ns / 1e6) if est.synced else 0
        out["link_latency_us"] = int(est.latency_s * 1e6)
        out["autopilot_system"] = self.identity.system if self.identity else 0
        return out

    # ------------------------------------------------------------------ the loop
    def step(self) -> int:
        transport = self.transport
        if transport is None:
            return 0
        clock = self.ctx.clock
        self._housekeeping(clock.realtime_ns())
        published = 0
        chunks = transport.recv(RECV_TIMEOUT_S)
        self.work_t0_ns = time.perf_counter_ns()  # the step's time excludes the wait
        batch: list[tuple[int, int, int, bytes]] = []
        for peer, data in chunks:
            arrival_ns = clock.realtime_ns()
            self.c["bytes_in"] += len(data)
            for frame in self._splitter.feed(data):
                transport.accept_peer(peer, True)
                batch.append((frame.src_system, frame.src_component, frame.msg_id, frame.data))
                published += self._frame(frame, arrival_ns)
        if batch:  # one hand-off per read, not per frame: the router's input
            self.ctx.state.queue(RX_QUEUE).put(batch)
        self.c["bad_frames"] = self._splitter.bad_crc
        self._command_attitude(clock.realtime_ns())
        self._send_queued()
        return published

    def _command_attitude(self, now_ns: int) -> None:
        """The control law's attitude, as SET_ATTITUDE_TARGET, while the autopilot is in the
        mode a companion flies in (ArduPlane's GUIDED, PX4's OFFBOARD) and the law is engaged
        with a fresh output. Nothing is sent otherwise: the pilot's or ground's mode change,
        or a control thread that stopped, hands the aircraft back to the autopilot (GUIDED
        holds the last target about 3 s, then its own guided behaviour).

        One exception, PX4's (`PX4_PRE`): PX4 refuses a switch to OFFBOARD unless setpoints
        already stream (MAVLink's offboard protocol), so while the law is switched on
        (`CTL_MODE` not off) and PX4 is in another mode, the law's disengaged output streams:
        wings level at its pitch set-point, the present heading. PX4 ignores them outside
        OFFBOARD; they are logged with `guided` 0."""
        ident = self.identity
        if ident is None or now_ns < self._next_command_ns:
            return
        out = self.ctx.state.control.read()
        if out is None or now_ns - out.t_ns > CONTROL_FRESH_S * 1e9:
            return
        flying = self.guided and out.enabled
        prestream = (not self.guided and ident.firmware == Firmware.PX4 and out.mode != "off"
                     and bool(self.param("PX4_PRE")))
        if not (flying or prestream):
            return
        self._next_command_ns = now_ns + int(1e9 / max(1, int(self.param("CMD_HZ"))))
        q = quat_from_euler_wxyz(out.roll_sp_rad, out.pitch_sp_rad, out.yaw_sp_rad)
        boot_ms = int(max(0, now_ns - self.sync.estimate().offset_ns) / 1e6) & 0xFFFFFFFF
        self._send(self._out.set_attitude_target_encode(
            boot_ms, ident.system, ident.component, _IGNORE_BODY_RATES, q, 0.0, 0.0, 0.0,
            float(min(max(out.throttle, 0.0), 1.0))))
        self.c["attitude_targets" if flying else "offboard_prestream"] += 1
        self._log(None, FMT_COMMAND, out.roll_sp_rad, out.pitch_sp_rad, out.yaw_sp_rad,
                  out.throttle, int(flying), t_ns=now_ns)

    def _send_queued(self) -> None:
        transport = self.transport
        assert transport is not None
        q = self.ctx.state.queue(TX_QUEUE)
        while (frame := q.get_nowait()) is not None:
            if transport.send(frame):
                self.c["frames_out"] += 1
            else:
                self.c["tx_failed"] += 1

    def _send(self, msg: Any) -> None:
        transport = self.transport
        if transport is None:
            return
        frame = msg.pack(self._out)
        self._out.seq = (self._out.seq + 1) & 0xFF  # pack() leaves the sequence where it is
        if transport.send(frame):
            self.c["frames_out"] += 1
        else:
            self.c["tx_failed"] += 1

    # ------------------------------------------------------------------ what arrives
    def _frame(self, frame: Frame, arrival_ns: int) -> int:
        """One whole frame (handed to the router as it came, by `step`): decoded if the link
        uses its kind."""
        self.c["frames"] += 1
        if frame.msg_id not in _USED:
            return 0  # forwarded only: decoding it (a third of this thread's time) buys nothing
        try:
            msg = self._decoder.decode(bytearray(frame.data))
        except Exception:  # a frame whose checksum held but whose content pymavlink refuses
            self.c["undecodable"] += 1
            return 0
        return self._handle(msg, (frame.src_system, frame.src_component), arrival_ns)

    def _handle(self, msg: Any, src: tuple[int, int], arrival_ns: int) -> int:
        msg_id = msg.get_msgId()
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            self._heartbeat(msg, src)
            return 1 if self._is_autopilot(src) else 0
        if not self._is_autopilot(src):
            self.c["foreign_frames"] += 1
            return 0
        self.streams.count(msg_id)
        stamp = message_time_ns(msg)
        gps = kind in ("GPS_RAW_INT", "GPS2_RAW")
        if stamp is None and gps:
            stamp = self._gps_boot_ns(msg)
        if stamp is not None and gps:
            # a fix's own time is older than the message that carries it (the receiver's
            # lag): it is mapped, but neither anchors the clock map nor tells a reboot
            t_ns = self.sync.map_or(stamp, arrival_ns)
        elif stamp is not None:
            resets = self.sync.resets
            self.sync.observe_stamp(stamp, arrival_ns)
            if self.sync.resets != resets:
                self._rebooted("its clock went back")
            t_ns = self.sync.map_or(stamp, arrival_ns)
            self._last_stamp_ns = t_ns
        elif kind == "SIMSTATE" and self._last_stamp_ns:
            # SIMSTATE carries no time: ArduPilot sends it in the same group as ATTITUDE, right
            # after it, so it is the simulator's state at that message's time
            t_ns = self._last_stamp_ns
        else:
            t_ns = arrival_ns
        if kind in IMU_MESSAGES:
            return self._imu(msg, kind, t_ns)
        if kind == "GPS_RAW_INT":
            fix = gps_fix(msg, t_ns)
            self.ctx.state.gps.write(fix)
            self._log("gps", FMT_SOLUTION, *FIX_LAYOUT.values(fix), t_ns=t_ns)
            self.c["gps_fixes"] += 1
        elif kind in ("ATTITUDE", "ATTITUDE_QUATERNION", "GLOBAL_POSITION_INT",
                      "EKF_STATUS_REPORT"):
            self._estimate_part(msg, kind, t_ns)
        elif kind == "GPS2_RAW":
            self.ctx.state.slot("gps2").write(gps_fix(msg, t_ns))  # a second receiver, apart
        elif kind == "BATTERY_STATUS":
            self._battery(msg, t_ns)
        elif kind == "RC_CHANNELS":
            self._rc = msg
        elif kind == "SERVO_OUTPUT_RAW":
            self._outputs = msg
            self._servo(t_ns)
        elif kind == "SIMSTATE":
            self._truth(msg, t_ns)
        elif kind == "SYSTEM_TIME" and msg.time_unix_usec > 0:
            # UNIX time against boot time: how a GPS fix's own time (UNIX) is mapped
            self._unix_minus_boot_ns = msg.time_unix_usec * 1000 - msg.time_boot_ms * 1_000_000
        elif kind == "TIMESYNC":
            self._timesync(msg, arrival_ns)
        elif kind == "COMMAND_ACK" and msg.result != apm.MAV_RESULT_ACCEPTED:
            self.c["acks_refused"] += 1
            log.debug("autopilot refused command %d: result %d", msg.command, msg.result)
            if (msg.command == apm.MAV_CMD_SET_MESSAGE_INTERVAL and not self.streams.data_streams
                    and self.identity is not None
                    and self.identity.firmware == Firmware.ARDUPILOT
                    and int(self.param("DSTREAM"))):
                self.streams.data_streams = True
                self.notice("autopilot refuses SET_MESSAGE_INTERVAL: asking with "
                            "REQUEST_DATA_STREAM, which sets its SRn_* rates on this port "
                            "until it reboots (AP_DSTREAM 0 stops this)", key="dstream")
                self._requests_again()
        return 0

    def _gps_boot_ns(self, msg: Any) -> int | None:
        """A GPS fix stamped in UNIX time, on the autopilot's boot clock (through SYSTEM_TIME),
        so the fix is dated when the receiver measured it, not when the stream sent it
        (ArduPilot stamps GPS_RAW_INT with the fix's boot time, which needs no mapping)."""
        usec = int(msg.time_usec)
        if self._unix_minus_boot_ns is None or usec < 10**15:
            return None
        boot_ns = usec * 1000 - self._unix_minus_boot_ns
        return boot_ns if boot_ns > 0 else None

    def _is_autopilot(self, src: tuple[int, int]) -> bool:
        ident = self.identity
        return ident is not None and src == (ident.system, ident.component)

    def _heartbeat(self, msg: Any, src: tuple[int, int]) -> None:
        if msg.autopilot == apm.MAV_AUTOPILOT_INVALID or msg.type in (
                apm.MAV_TYPE_GCS, apm.MAV_TYPE_ONBOARD_CONTROLLER):
            return  # a ground station or a companion behind the autopilot, not the autopilot
        wanted = int(self.param("SYSID"))
        if wanted and src[0] != wanted:
            self.c["foreign_frames"] += 1
            return
        ident = self.identity
        if ident is not None and src != (ident.system, ident.component):
            if (ident.system, ident.component) in self._recent_sources():
                self.c["foreign_frames"] += 1
                return  # a second autopilot: the first one stays the one we follow
            self.c["system_changes"] += 1
            self.notice(f"autopilot is now system {src[0]} component {src[1]} "
                        f"(was {ident.system}/{ident.component})", key="sysid")
            self.sync.reset()
            self._requests_again()
        self.c["heartbeats"] += 1
        firmware = Firmware.of(msg.autopilot)
        new = AutopilotIdentity(src[0], src[1], firmware, msg.type)
        if new != ident:
            self.identity = new
            self._out.srcSystem = src[0]  # the companion is a component of the same system
            self._log(None, FMT_HEARTBEAT, src[0], src[1], msg.autopilot, msg.type,
                      msg.base_mode, msg.custom_mode, msg.system_status,
                      t_ns=self.ctx.clock.realtime_ns())
            log.info("autopilot: system %d component %d, %s", src[0], src[1], firmware)
            self._requests_again()
        self.guided = (msg.custom_mode == _ARDUPLANE_GUIDED if firmware == Firmware.ARDUPILOT
                       else msg.custom_mode == _PX4_OFFBOARD if firmware == Firmware.PX4
                       else False)
        self._last_heartbeat_ns = self.ctx.clock.monotonic_ns()

    def _recent_sources(self) -> set[tuple[int, int]]:
        """The autopilot we follow still beats (a HEARTBEAT within 3 s)."""
        last = self._last_heartbeat_ns
        if self.identity is None or self.ctx.clock.monotonic_ns() - last > 3e9:
            return set()
        return {(self.identity.system, self.identity.component)}

    def _rebooted(self, why: str) -> None:
        self.c["reboots"] += 1
        self.notice(f"autopilot rebooted ({why}): clock map and stream requests start again",
                    key="reboot")
        self._requests_again()

    def _requests_again(self) -> None:
        self._next_request_ns = 0
        self.streams.again()

    def _imu(self, msg: Any, kind: str, t_ns: int) -> int:
        # the most preferred IMU message that arrives at all is the only one used
        if self._imu_kind is None or IMU_MESSAGES.index(kind) < IMU_MESSAGES.index(
                self._imu_kind):
            self._imu_kind = kind
        if kind != self._imu_kind or self.identity is None:
            return 0
        sample = imu_sample(msg, self.identity.firmware, t_ns, self._imu_counter)
        if sample is None:
            return 0
        self._imu_counter += 1
        state = self.ctx.state
        state.imu.write(sample)
        state.imu_stream.put(sample)
        self._log("imu", FMT_FAST, sample.counter, 0, *sample.rates_rad_s, *sample.accel_m_s2,
                  t_ns=t_ns)
        temp = imu_temperature_c(msg)
        if temp is not None and self._imu_counter % 50 == 1:  # a slow sample once a second
            slow = ImuSlowSample(t_ns, sample.rates_rad_s, sample.accel_m_s2, temp, 0)
            state.imu_slow.write(slow)
            self._log("imu", FMT_SLOW, *slow.rates_rad_s, *slow.accel_m_s2, temp, 0, t_ns=t_ns)
        self.c["imu_samples"] += 1
        return 1

    def _estimate_part(self, msg: Any, kind: str, t_ns: int) -> None:
        est = self._estimate
        if kind == "GLOBAL_POSITION_INT":
            est.update(lat_deg=msg.lat / 1e7, lon_deg=msg.lon / 1e7, alt_m=msg.alt / 1000.0,
                       vn_m_s=msg.vx / 100.0, ve_m_s=msg.vy / 100.0, vd_m_s=msg.vz / 100.0)
            return
        if kind == "EKF_STATUS_REPORT":
            est["ekf_flags"] = int(msg.flags)
            return
        # ATTITUDE where it comes, else ATTITUDE_QUATERNION (one of the two, never both)
        if self._attitude_kind is None or kind == "ATTITUDE":
            self._attitude_kind = kind
        if kind != self._attitude_kind:
            return
        if kind == "ATTITUDE":
            roll, pitch, yaw = msg.roll, msg.pitch, msg.yaw
        else:
            roll, pitch, yaw = euler_from_quat(msg.q1, msg.q2, msg.q3, msg.q4)
        sample = AutopilotEstimate(t_ns, roll, pitch, yaw, msg.rollspeed,
                                   msg.pitchspeed, msg.yawspeed, **est)
        self.ctx.state.slot("autopilot").write(sample)
        self._log(None, FMT_ESTIMATE, sample.roll_rad, sample.pitch_rad, sample.yaw_rad,
                  sample.rollspeed_rad_s, sample.pitchspeed_rad_s, sample.yawspeed_rad_s,
                  *(math.nan if v is None else v for v in (
                      sample.lat_deg, sample.lon_deg, sample.alt_m, sample.vn_m_s,
                      sample.ve_m_s, sample.vd_m_s)), sample.ekf_flags, t_ns=t_ns)
        self.c["estimates"] += 1

    def _battery(self, msg: Any, t_ns: int) -> None:
        cells = [v for v in msg.voltages if v != 0xFFFF]
        self.ctx.state.slot("battery").write(BatterySample(
            t_ns, int(msg.id), sum(cells) / 1000.0 if cells else None,
            msg.current_battery / 100.0 if msg.current_battery >= 0 else None,
            int(msg.battery_remaining) if msg.battery_remaining >= 0 else None))

    def _servo(self, t_ns: int) -> None:
        self._servo_seq += 1
        st = servo_state(self._rc, self._outputs, t_ns, self._servo_seq, self.guided)
        self.ctx.state.servo.write(st)
        self._log("servo", FMT_EXCHANGE, *(min(v, 0xFFFF) for v in st.pilot_us),
                  *(min(v, 0xFFFF) for v in st.computer_us), st.seq, int(st.auto_requested),
                  int(st.auto_engaged), int(st.failsafe), 0, 0, t_ns=t_ns)

    def _truth(self, msg: Any, t_ns: int) -> None:
        truth = truth_sample(msg, t_ns)
        if truth is None:
            return
        self.ctx.state.slot("truth").write(truth)
        nan = math.nan
        self._log("truth", FMT_TRUTH, truth.roll_rad, truth.pitch_rad, truth.yaw_rad,
                  nan, nan, nan, nan, nan, nan, *truth.rates_rad_s, *truth.accel_m_s2,
                  truth.lat_deg, truth.lon_deg, nan, nan, t_ns / 1e9, t_ns=t_ns)
        self.c["truth_samples"] += 1

    def _timesync(self, msg: Any, arrival_ns: int) -> None:
        if msg.tc1 == 0:
            return  # the autopilot's own request: the ground stations answer it
        sent = self._pending_sync.pop(int(msg.ts1), None)
        if sent is None:
            return
        if self.sync.observe_round_trip(sent, int(msg.tc1), arrival_ns):
            self.c["time_syncs"] += 1
            est = self.sync.estimate()
            self._log(None, FMT_TSYNC, est.offset_ns / 1e6, est.drift_ppm, est.latency_s * 1e3,
                      est.rtt_s * 1e3, int(est.synced), est.resets, t_ns=arrival_ns)

    # ------------------------------------------------------------------ what we send
    def _housekeeping(self, now_ns: int) -> None:
        if now_ns >= self._next_heartbeat_ns:
            self._next_heartbeat_ns = now_ns + 1_000_000_000
            self._send(self._out.heartbeat_encode(
                apm.MAV_TYPE_ONBOARD_CONTROLLER, apm.MAV_AUTOPILOT_INVALID, 0, 0,
                apm.MAV_STATE_ACTIVE))
        ident = self.identity
        if ident is None:
            return
        if now_ns >= self._next_sync_ns:
            self._next_sync_ns = now_ns + int(self.param("SYNC_MS")) * 1_000_000
            if len(self._pending_sync) > 16:
                self._pending_sync.clear()
            self._pending_sync[now_ns] = now_ns
            self._send(self._out.timesync_encode(0, now_ns))
        if now_ns >= self._next_request_ns:
            self._next_request_ns = now_ns + int(REQUEST_EVERY_S * 1e9)
            self._request_streams(ident)

    def _request_streams(self, ident: AutopilotIdentity) -> None:
        for msg in self.streams.requests(self._out, ident.system, ident.component,
                                         ident.firmware == Firmware.PX4,
                                         lambda suffix: int(self.param(suffix))):
            self.c["requests"] += 1
            self._send(msg)

    def _log(self, name: str | None, fmt: int, *values: float | int, t_ns: int) -> None:
        tlog = self.tlog if name is None else self._logs.get(name)
        if tlog is not None:
            tlog.log(fmt, *values, t_ns=t_ns)

