"""The ground truth of a simulated flight: one SI dataclass in the project's frames.

Everything in SITL (device simulators, the scripted pilot, the on-board runtime, estimator
benchmarks) is judged against a `TruthState`; the flight model (`companion.sim.flight`) fills
it from JSBSim. Its own module so that what reads the truth needs no JSBSim.
"""

from __future__ import annotations

from dataclasses import dataclass

from companion.core.fastinit import fast_frozen

__all__ = ["TruthState"]


@fast_frozen
@dataclass(frozen=True)
class TruthState:
    """True aircraft state at one instant, SI units.

    Frames: NED for positions and velocities (position relative to the start point, on the
    tangent plane of :class:`companion.core.geo.NedFrame`), body axes x forward, y right, z down
    for rates and specific force. Euler angles are the usual yaw-pitch-roll (3-2-1) sequence,
    ``yaw_rad`` in (-pi, pi] from true north. Body rates are inertial (what a gyro measures; they
    differ from earth-relative rates by at most the earth rate, 7.3e-5 rad/s). Specific force is
    the non-gravitational force per unit mass at the IMU, which sits at the centre of gravity:
    what an accelerometer measures, about (0, 0, -9.8) in level flight. ``alt_m`` is height
    above the WGS-84 ellipsoid, which is mean sea level in this simulator. ``airspeed_m_s`` is
    true airspeed; ``alpha_rad`` and ``beta_rad`` are angle of attack and sideslip.
    """

    time_s: float
    lat_deg: float
    lon_deg: float
    alt_m: float
    north_m: float
    east_m: float
    down_m: float
    vn_m_s: float
    ve_m_s: float
    vd_m_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    p_rad_s: float
    q_rad_s: float
    r_rad_s: float
    ax_m_s2: float
    ay_m_s2: float
    az_m_s2: float
    airspeed_m_s: float
    alpha_rad: float = 0.0
    beta_rad: float = 0.0
