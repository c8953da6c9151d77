"""The aircraft's state as legacy protocol messages: THREAD_STATUS and the thread data messages.

Each builder reads one slot of the runtime's shared state (or one managed thread's status) and
returns the message the legacy monitor shows, or None while the slot is still empty. It is the
translation between the runtime's vocabulary and the protocol's; the adapter
(:mod:`legacy_protocol.adapter`) only decides when to send, and over which socket.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from companion.watchdog import ManagedThread, RuntimeContext
from legacy_protocol import messages

__all__ = ["DATA_MESSAGES", "thread_status"]


def thread_status(t: ManagedThread) -> messages.ThreadStatus:
    """One managed thread's status as the THREAD_STATUS message."""
    s = t.status()
    flags = (
        (messages.ThreadFlag.INITIALISED if s.initialised else 0)
        | (messages.ThreadFlag.RUNNING if s.running else 0)
        | (messages.ThreadFlag.IN_PERIODIC if s.in_periodic else 0)
        | (messages.ThreadFlag.ALIVE if s.alive else 0)
    )
    return messages.ThreadStatus(
        s.thread_id,
        int(flags),
        min(s.restarts, 0xFFFF),
        min(int(s.mean_step_us), 0xFFFFFFFF),
        s.watchdog_ms,
        s.message_ms,
        s.name[:16],
    )


def _f(x: float | None) -> float:
    return math.nan if x is None else float(x)


def _imu(ctx: RuntimeContext, t: ManagedThread) -> messages.Imu | None:
    s = ctx.state.imu.read()
    if s is None:
        return None
    slow = ctx.state.imu_slow.read()
    return messages.Imu(
        *s.rates_rad_s,
        *s.accel_m_s2,
        slow.temperature_c if slow is not None else math.nan,
        t.cycles & 0xFFFFFFFF,
    )


def _gps(ctx: RuntimeContext, t: ManagedThread) -> messages.Gps | None:
    g = ctx.state.gps.read()
    if g is None:
        return None
    return messages.Gps(
        _f(g.lat_deg),
        _f(g.lon_deg),
        _f(g.alt_m),
        _f(g.vn_m_s),
        _f(g.ve_m_s),
        _f(g.vd_m_s),
        _f(g.pdop),
        _f(g.hdop),
        _f(g.vdop),
        _f(g.tdop),
        _f(None if g.latency_s is None else g.latency_s * 1e3),
        _f(g.alt_std_m),
        max(0, min(3, g.fix)),
        min(g.sats or 0, 255),
    )


def _servo(ctx: RuntimeContext, t: ManagedThread) -> messages.Servo | None:
    s = ctx.state.servo.read()
    if s is None:
        return None
    flags = (messages.ServoFlag.AUTOMATIC if s.auto_engaged else 0) | (
        messages.ServoFlag.FAILSAFE if s.failsafe else 0
    )
    return messages.Servo(
        tuple(s.pilot_us[:8]),
        tuple(s.computer_us[:8]),
        s.avionics_batt_raw,
        s.servo_batt_raw,
        int(flags),
    )


def _estimator(ctx: RuntimeContext, t: ManagedThread) -> messages.Estimator | None:
    e = ctx.state.estimator.read()
    if e is None:
        return None
    return messages.Estimator(
        e.roll_rad, e.pitch_rad, e.yaw_rad, *e.pos_ned_m, *e.vel_ned_m_s, *e.gyro_bias_rad_s
    )


def _control(ctx: RuntimeContext, t: ManagedThread) -> messages.Control | None:
    c = ctx.state.control.read()
    if c is None:
        return None
    return messages.Control(c.aileron, c.elevator, c.rudder, c.throttle, int(c.enabled))


DataBuilder = Callable[[RuntimeContext, ManagedThread], messages.Message | None]

DATA_MESSAGES: dict[str, DataBuilder] = {
    "imu": _imu,
    "gps": _gps,
    "servo": _servo,
    "estimator": _estimator,
    "control": _control,
}
