"""The ESKF's delayed-state history: where the aircraft was when a late measurement was taken.

A GPS fix or a horizon frame describes an instant some 50-300 ms before it reaches the filter;
the updates compare it with the state of that instant, kept here sample by sample, and the
last healthy state is kept for a fault's repair. Separate because it is bookkeeping the updates
read, not filter mathematics.
"""

from __future__ import annotations

from companion.estimation.eskf_state import (
    EskfBase,
    Vec3f,
)


class StateHistory(EskfBase):
    """The state after each sample, for measurements that arrive late."""

    def _remember_good(self) -> None:
        self._last_good = (self._q, self._pos, self._vel)

    def _state_at_f(self, t_s: float) -> tuple[Vec3f, Vec3f, tuple[float, ...]] | None:
        """Nominal position, velocity and attitude at ``t_s`` from the history (interpolated;
        the attitude is the nearer stored one), as floats; None before the history."""
        if t_s >= self._t - 1e-9 or not self._history:
            return self._pos_f, self._vel_f, self._q
        newer = None
        for entry in reversed(self._history):
            if entry[0] <= t_s:
                if newer is None:
                    return entry[1], entry[2], entry[3]
                t0, t1 = entry[0], newer[0]
                a = (t_s - t0) / (t1 - t0) if t1 > t0 else 0.0
                p0, v0, p1, v1 = entry[1], entry[2], newer[1], newer[2]
                pos = (p0[0] + a * (p1[0] - p0[0]), p0[1] + a * (p1[1] - p0[1]),
                       p0[2] + a * (p1[2] - p0[2]))
                vel = (v0[0] + a * (v1[0] - v0[0]), v0[1] + a * (v1[1] - v0[1]),
                       v0[2] + a * (v1[2] - v0[2]))
                return pos, vel, (newer[3] if a >= 0.5 else entry[3])
            newer = entry
        return None

    def _mean_accel_at(self, t_s: float, half_window_s: float = 0.05) -> Vec3f:
        """NED acceleration around ``t_s`` as a velocity difference over +-``half_window_s``.

        Not the sample's own acceleration: one sample carries the accelerometer's white noise
        (0.5 m/s^2 at 100 Hz for a consumer part), and as the delay's Jacobian that noise would
        make the delay look observable in straight flight, where it is not.
        """
        lo = self._state_at_f(t_s - half_window_s)
        hi = self._state_at_f(min(t_s + half_window_s, self._t))
        if lo is None or hi is None:
            return (0.0, 0.0, 0.0)
        span = min(t_s + half_window_s, self._t) - (t_s - half_window_s)
        if not span > 1e-6:
            return (0.0, 0.0, 0.0)
        v0, v1 = lo[1], hi[1]
        return ((v1[0] - v0[0]) / span, (v1[1] - v0[1]) / span, (v1[2] - v0[2]) / span)
