"""Control thread: PID wing leveller, attitude hold, altitude and heading hold.

Paced by the estimator: each new estimate produces one command. The law is *active* only when
CTL_MODE selects one and the pilot's mode switch engages automatic mode; the servo thread asks
the board for automatic control only while the output says so, and the board always obeys the
pilot's switch first, so the pilot taking control back wins at once.

Sign convention of `ControlOutput` (the same as JSBSim's normalised commands, and the same pulse
mapping as the pilot's sticks): aileron +1 rolls right, elevator +1 pitches the nose *down*
(stick forward), rudder +1 yaws the nose left, throttle 0 idle .. 1 full.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

from companion.core.mathutil import clamp, wrap_pi
from companion.core.params import ParamSpec, float_param, int_param
from companion.core.state import ControlOutput, EstimatorState
from companion.watchdog.thread import ManagedThread, Task

MODE_OFF, MODE_LEVEL, MODE_ATTITUDE, MODE_LEVEL_ALT, MODE_HEADING_ALT = 0, 1, 2, 3, 4
MODE_NAMES = {MODE_OFF: "off", MODE_LEVEL: "level", MODE_ATTITUDE: "attitude",
              MODE_LEVEL_ALT: "level+alt", MODE_HEADING_ALT: "heading+alt"}
FMT_CONTROL = 1


@dataclass
class Pid:
    """PID on an error with the derivative taken from a measured rate (no derivative kick) and
    a clamped integrator (no wind-up while the output saturates)."""

    kp: float
    ki: float
    kd: float
    i_limit: float
    integral: float = 0.0

    def update(self, error: float, rate: float, dt_s: float) -> float:
        self.integral = clamp(self.integral + error * dt_s, -self.i_limit, self.i_limit)
        return self.kp * error + self.ki * self.integral - self.kd * rate

    def reset(self) -> None:
        self.integral = 0.0


@dataclass(frozen=True)
class _Settings:
    """The control law's parameters, typed and in SI units, as of the last change."""

    mode: int
    roll_max_rad: float
    pitch_max_rad: float
    pitch_sp_rad: float
    roll_sp_rad: float
    hdg_kp: float
    alt_kp: float
    vz_kd: float


class ControlThread(ManagedThread):
    def __init__(self, *, task: Task) -> None:
        super().__init__(task)
        self._seen = 0
        self._engaged = False
        self._alt_sp_m = 0.0
        self._hdg_sp_rad = 0.0
        self._throttle = 0.6
        self._last_t_ns = 0
        self.roll_pid = Pid(1.2, 0.1, 0.15, 0.3)
        self.pitch_pid = Pid(2.0, 0.3, 0.3, 0.3)
        self._settings: _Settings | None = None  # read on start and on a change, not per step

    @classmethod
    def declare_params(cls, p: str) -> list[ParamSpec]:
        return [
            int_param(f"{p}_MODE", MODE_LEVEL_ALT, 0, 4, "",
                      "Control law: 0 off, 1 wings level, 2 attitude hold, 3 wings level + "
                      "altitude hold, 4 heading + altitude hold. Acts only in automatic mode."),
            float_param(f"{p}_ROLL_KP", 1.2, 0.0, 10.0, "1/rad", "Roll loop proportional gain."),
            float_param(f"{p}_ROLL_KI", 0.1, 0.0, 10.0, "1/(rad s)", "Roll loop integral gain."),
            float_param(f"{p}_ROLL_KD", 0.15, 0.0, 10.0, "s/rad", "Roll loop damping on roll rate."),
            float_param(f"{p}_PTCH_KP", 2.0, 0.0, 10.0, "1/rad", "Pitch loop proportional gain."),
            float_param(f"{p}_PTCH_KI", 0.3, 0.0, 10.0, "1/(rad s)", "Pitch loop integral gain."),
            float_param(f"{p}_PTCH_KD", 0.3, 0.0, 10.0, "s/rad", "Pitch loop damping on pitch rate."),
            float_param(f"{p}_ALT_KP", 0.02, 0.0, 1.0, "rad/m",
                        "Altitude hold: pitch set-point per metre of altitude error."),
            float_param(f"{p}_VZ_KD", 0.03, 0.0, 1.0, "rad/(m/s)",
                        "Altitude hold: pitch set-point per m/s of climb-rate error."),
            float_param(f"{p}_HDG_KP", 1.0, 0.0, 5.0, "rad/rad",
                        "Heading hold: bank set-point per radian of heading error."),
            float_param(f"{p}_ROLL_MAX", 35.0, 5.0, 60.0, "deg", "Largest bank the law commands."),
            float_param(f"{p}_PTCH_MAX", 15.0, 2.0, 30.0, "deg", "Largest pitch the law commands."),
            float_param(f"{p}_ROLL_SP", 0.0, -60.0, 60.0, "deg", "Attitude-hold bank set-point."),
            float_param(f"{p}_PTCH_SP", 2.0, -30.0, 30.0, "deg",
                        "Pitch set-point for wings-level and attitude hold."),
        ]

    def define_logs(self, tlog: Any) -> None:
        tlog.define(FMT_CONTROL, "%hhu,%hhu,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f,%.2f,%.4f",
                    ["mode", "enabled", "aileron", "elevator", "rudder", "throttle",
                     "roll_sp_rad", "pitch_sp_rad", "alt_sp_m", "hdg_sp_rad"])

    def _tune(self) -> _Settings:
        """Read this thread's parameters once, typed, into the gains and the step's settings."""
        g = self.param
        self.roll_pid.kp, self.roll_pid.ki, self.roll_pid.kd = g("ROLL_KP"), g("ROLL_KI"), g("ROLL_KD")
        self.pitch_pid.kp, self.pitch_pid.ki, self.pitch_pid.kd = g("PTCH_KP"), g("PTCH_KI"), g("PTCH_KD")
        self._settings = _Settings(
            mode=int(g("MODE")), roll_max_rad=math.radians(g("ROLL_MAX")),
            pitch_max_rad=math.radians(g("PTCH_MAX")), pitch_sp_rad=math.radians(g("PTCH_SP")),
            roll_sp_rad=math.radians(g("ROLL_SP")), hdg_kp=float(g("HDG_KP")),
            alt_kp=float(g("ALT_KP")), vz_kd=float(g("VZ_KD")))
        return self._settings

    def prologue(self) -> bool:
        """Wait for the estimator's first output: until then there is nothing to control, and
        the wait is not a stall."""
        self._tune()
        self._engaged = False
        slot = self.ctx.state.estimator
        while slot.read() is None:
            if self.ctx.clock.sleep(0.05, self.stop_event):
                return False
        self._seen = 0
        return True

    def on_params_changed(self) -> None:
        self._tune()

    def recover(self) -> None:
        self.roll_pid.reset()
        self.pitch_pid.reset()
        self._engaged = False

    def _pilot_auto(self) -> tuple[bool, float]:
        servo = self.ctx.state.servo.read()
        if servo is None or servo.failsafe:
            return False, self._throttle
        return servo.pilot_auto_switch, servo.pilot_throttle

    def step(self) -> bool:
        got = self.ctx.state.estimator.wait_newer(self._seen, 0.05, self.ctx.clock)
        if got is None:
            return False
        self.work_t0_ns = time.perf_counter_ns()  # step time excludes the wait
        est, self._seen = got
        if est is None:
            return False
        self.compute(est)
        return True

    def compute(self, est: EstimatorState) -> ControlOutput:
        cfg = self._settings if self._settings is not None else self._tune()
        mode = cfg.mode
        pilot_auto, pilot_throttle = self._pilot_auto()
        active = mode != MODE_OFF and pilot_auto and est.aligned
        dt_s = 0.01 if not self._last_t_ns else clamp((est.t_ns - self._last_t_ns) / 1e9, 1e-3, 0.1)
        self._last_t_ns = est.t_ns
        alt_m = (est.origin_alt_m or 0.0) - est.pos_ned_m[2]
        if active and not self._engaged:
            # capture the references at engagement: hold what the aircraft was doing
            self._alt_sp_m = alt_m
            self._hdg_sp_rad = est.yaw_rad
            self._throttle = pilot_throttle
            self.roll_pid.reset()
            self.pitch_pid.reset()
        self._engaged = active
        roll_max = cfg.roll_max_rad
        pitch_max = cfg.pitch_max_rad
        roll_sp = 0.0
        pitch_sp = cfg.pitch_sp_rad
        if mode == MODE_ATTITUDE:
            roll_sp = cfg.roll_sp_rad
        if mode == MODE_HEADING_ALT:
            roll_sp = clamp(cfg.hdg_kp * wrap_pi(self._hdg_sp_rad - est.yaw_rad),
                            -roll_max, roll_max)
        if mode in (MODE_LEVEL_ALT, MODE_HEADING_ALT):
            climb_m_s = -est.vel_ned_m_s[2]
            pitch_sp = cfg.alt_kp * (self._alt_sp_m - alt_m) - cfg.vz_kd * climb_m_s
        roll_sp = clamp(roll_sp, -roll_max, roll_max)
        pitch_sp = clamp(pitch_sp, -pitch_max, pitch_max)
        p, q, _r = est.rates_rad_s
        if active:
            aileron = clamp(self.roll_pid.update(wrap_pi(roll_sp - est.roll_rad), p, dt_s), -1, 1)
            # elevator +1 is nose down: a positive pitch error needs a negative command
            elevator = clamp(-self.pitch_pid.update(pitch_sp - est.pitch_rad, q, dt_s), -1, 1)
            rudder = 0.0
            throttle = self._throttle
        else:
            aileron = elevator = rudder = 0.0
            throttle = pilot_throttle
        yaw_sp = self._hdg_sp_rad if mode == MODE_HEADING_ALT else est.yaw_rad
        out = ControlOutput(self.ctx.clock.realtime_ns(), aileron, elevator, rudder, throttle,
                            active, MODE_NAMES.get(mode, "?"), roll_sp, pitch_sp, yaw_sp)
        self.ctx.state.control.write(out)
        if self.tlog is not None:
            self.tlog.log(FMT_CONTROL, mode, int(active), aileron, elevator, rudder, throttle,
                          roll_sp, pitch_sp, self._alt_sp_m, self._hdg_sp_rad, t_ns=out.t_ns)
        return out
