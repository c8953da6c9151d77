"""The vehicle's shared state: one data slot per producer, read by everyone downstream.

Data flows one way: drivers -> slots -> estimator -> control -> servo. Bridges only read these
slots (and post commands to the manager or set parameters). Every value is a frozen dataclass, so
the reference a reader takes from a slot is a consistent snapshot. Units are SI; MAVLink scaling
happens only in the bridge.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any

from companion.core.fastinit import fast_frozen
from companion.core.logged import logged
from companion.core.sync import DataSlot, MessageQueue, WaitableSlot

Vec3 = tuple[float, float, float]


@fast_frozen
@dataclass(frozen=True)
class ImuSample:
    """One fast IMU frame, converted: body rates (rad/s) and specific force (m/s^2), x fwd y right z down."""

    t_ns: int  # runtime realtime clock at reception
    counter: int
    rates_rad_s: Vec3
    accel_m_s2: Vec3
    gyro_ok: bool = True
    accel_ok: bool = True
    counter_period_s: float = 0.01
    """What one step of `counter` is in time (the thesis IMU counts its 10 ms frames), so a
    sample's period is counted, not measured; 0: no such counter (an autopilot's IMU at the
    rate its stream gives), the period is the difference of the samples' times."""


@fast_frozen
@dataclass(frozen=True)
class ImuSlowSample:
    """The once-per-second high-resolution block."""

    t_ns: int
    rates_rad_s: Vec3
    accel_m_s2: Vec3
    temperature_c: float
    bit_word: int


@fast_frozen
@dataclass(frozen=True)
class GpsFix:
    """One GPS solution (one epoch) as the flight uses it; None where the receiver did not say.

    This is also the GPS driver's log record: each `logged` field is a column of `gps.bin`
    format 1, in this order, so the record, its log format and its log call cannot disagree.
    """

    t_ns: int  # hand-off time, runtime clock (the log record's own time stamp)
    utc_s: float | None = logged("%.3f")  # seconds since midnight UTC of the epoch
    lat_deg: float | None = logged("%.9lf")
    lon_deg: float | None = logged("%.9lf")
    alt_m: float | None = logged("%.3f")  # above mean sea level
    fix: int = logged("%hhu", default=0)  # 0 none, 1 GPS, 2 DGPS, 3 RTK
    sats: int | None = logged("%hhu")
    hdop: float | None = logged("%.2f")
    pdop: float | None = logged("%.2f")
    vdop: float | None = logged("%.2f")
    tdop: float | None = logged("%.2f")
    speed_m_s: float | None = logged("%.3f")
    course_deg: float | None = logged("%.2f")
    vn_m_s: float | None = logged("%.3f")
    ve_m_s: float | None = logged("%.3f")
    vd_m_s: float | None = logged("%.3f")
    alt_std_m: float | None = logged("%.3f")
    h_std_m: float | None = logged("%.3f")
    latency_s: float | None = logged("%.2f", column="latency_ms", scale=1e3)
    """Receiver-to-driver latency as measured by the driver (first byte to hand-off)."""
    heading_deg: float | None = logged("%.2f")
    """True heading of a dual-antenna receiver's baseline (HDT), 0..360; None without one."""


@fast_frozen
@dataclass(frozen=True)
class ServoState:
    """One servo-board exchange: what the pilot commanded and what the computer sent.

    The pulse widths are the exchange's record (logged, and sent as MAVLink's RC_CHANNELS and
    SERVO_OUTPUT_RAW, whose unit they are); what the flight reads of the pilot is normalised by
    the driver (`pilot_auto_switch`, `pilot_throttle`), so no reader decodes microseconds."""

    t_ns: int
    seq: int
    pilot_us: tuple[int, ...]
    computer_us: tuple[int, ...]
    auto_requested: bool
    auto_engaged: bool
    failsafe: bool
    avionics_batt_raw: int
    servo_batt_raw: int
    pilot_auto_switch: bool = False
    """The pilot's mode switch selects automatic mode (what the control law engages on)."""
    pilot_throttle: float = 0.0
    """The pilot's throttle stick, 0..1."""


@fast_frozen
@dataclass(frozen=True)
class EstimatorState:
    t_ns: int
    quat_wxyz: tuple[float, float, float, float]
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    pos_ned_m: Vec3  # from the origin below
    vel_ned_m_s: Vec3
    gyro_bias_rad_s: Vec3
    accel_bias_m_s2: Vec3
    origin_lat_deg: float | None
    origin_lon_deg: float | None
    origin_alt_m: float | None
    cov_diag: tuple[float, ...] = ()
    innovations: tuple[float, ...] = ()
    rates_rad_s: Vec3 = (0.0, 0.0, 0.0)
    aligned: bool = False
    faults: int = 0


@fast_frozen
@dataclass(frozen=True)
class ControlOutput:
    """Normalised surface commands: aileron/elevator/rudder -1..1, throttle 0..1."""

    t_ns: int
    aileron: float
    elevator: float
    rudder: float
    throttle: float
    enabled: bool  # the control law is active (parameter on and pilot engaged automatic mode)
    mode: str = "off"
    roll_sp_rad: float = 0.0
    """The attitude the law flies to (what a flight controller is asked to hold in GUIDED,
    where the surfaces above are its business)."""
    pitch_sp_rad: float = 0.0
    yaw_sp_rad: float = 0.0


@fast_frozen
@dataclass(frozen=True)
class HorizonMeasurement:
    """Attitude from horizon detection on the ground, sent back to the aircraft."""

    t_ns: int  # time of the video frame
    roll_rad: float
    pitch_rad: float
    quality: float  # 0..1
    source: str = "legacy"


@dataclass
class VehicleState:
    """All slots of one vehicle. Producers write, everyone else reads."""

    imu: WaitableSlot[ImuSample] = field(default_factory=WaitableSlot)
    # every IMU sample, for the estimator, which must integrate all of them, not just the newest
    imu_stream: MessageQueue[ImuSample] = field(
        default_factory=lambda: MessageQueue(512, drop_oldest=True))
    imu_slow: DataSlot[ImuSlowSample] = field(default_factory=DataSlot)
    gps: WaitableSlot[GpsFix] = field(default_factory=WaitableSlot)
    servo: DataSlot[ServoState] = field(default_factory=DataSlot)
    estimator: WaitableSlot[EstimatorState] = field(default_factory=WaitableSlot)
    control: DataSlot[ControlOutput] = field(default_factory=DataSlot)
    horizon: DataSlot[HorizonMeasurement] = field(default_factory=DataSlot)
    named: dict[str, WaitableSlot[Any]] = field(default_factory=dict, repr=False)
    """Slots of kinds of data the fields above do not have (a plug-in source's airspeed, a
    barometer), by name: see `slot`."""
    queues: dict[str, MessageQueue[Any]] = field(default_factory=dict, repr=False)
    """Named queues between a source and the bridges (an autopilot's frames to route, and the
    frames to send it): see `queue`."""
    _named_lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def queue(self, name: str, capacity: int = 4096) -> MessageQueue[Any]:
        """The bounded queue `name` (created on first use, the oldest item dropped when full):
        how a bridge and a source hand each other items without knowing each other."""
        with self._named_lock:
            q = self.queues.get(name)
            if q is None:
                q = self.queues[name] = MessageQueue(capacity, drop_oldest=True)
            return q

    def slot(self, name: str) -> WaitableSlot[Any]:
        """The slot `name`: a field above when there is one (``imu``, ``gps``...), else a named
        slot created on first use, so a new source publishes a new kind of data without a
        field here. Producer and readers agree on the name (the source's row lists it in
        ``publishes``)."""
        own = getattr(self, name, None) if not name.startswith("_") else None
        if isinstance(own, DataSlot):
            return own  # type: ignore[return-value]
        with self._named_lock:
            slot = self.named.get(name)
            if slot is None:
                slot = self.named[name] = WaitableSlot()
            return slot
