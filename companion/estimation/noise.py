"""The two closed forms the flight filter needs from probability: a chi-square gate and the
process noise of a white-acceleration model.

Why not scipy.stats and filterpy here, when the project prefers libraries: both are used for
one number each, computed once, and importing them costs about half a second (scipy.stats
0.48 s, filterpy 0.48 s, mostly the same scipy modules) in every runtime start, every
campaign flight and the estimator thread's first start. The closed forms below are exact, and
``tests/test_estimation_noise.py`` checks them against ``scipy.stats.chi2.ppf`` and
``filterpy.common.Q_continuous_white_noise`` so they cannot drift from the libraries.
"""

from __future__ import annotations

import math

import numpy as np

from companion.estimation.quat import FloatArray

__all__ = ["chi2_cdf_even", "chi2_ppf_even", "white_accel_q"]


def chi2_cdf_even(x: float, dof: int) -> float:
    """P(X <= x) for a chi-square variable with an even number of degrees of freedom.

    For even ``dof`` the distribution is an Erlang one: ``1 - exp(-x/2) * sum_{k < dof/2}
    (x/2)^k / k!``, exact and cheap.
    """
    if dof <= 0 or dof % 2:
        raise ValueError(f"dof must be a positive even integer, got {dof}")
    if x <= 0.0:
        return 0.0
    half = 0.5 * x
    term = 1.0
    total = 1.0
    for k in range(1, dof // 2):
        term *= half / k
        total += term
    return 1.0 - math.exp(-half) * total


def chi2_ppf_even(p: float, dof: int) -> float:
    """The chi-square quantile for an even ``dof``: the gate a normalised innovation squared
    (NIS) of ``dof`` components exceeds with probability ``1 - p``.

    Solved by bisection on :func:`chi2_cdf_even` to a relative 1e-12 (about 60 halvings,
    microseconds, done once per filter).
    """
    if not 0.0 < p < 1.0:
        raise ValueError(f"p must be in (0, 1), got {p}")
    if dof <= 0 or dof % 2:
        raise ValueError(f"dof must be a positive even integer, got {dof}")
    if dof == 2:
        return -2.0 * math.log1p(-p)  # exponential distribution, closed form
    lo, hi = 0.0, float(dof)
    while chi2_cdf_even(hi, dof) < p:
        hi *= 2.0
    while hi - lo > 1e-12 * hi:
        mid = 0.5 * (lo + hi)
        if chi2_cdf_even(mid, dof) < p:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def white_accel_q(dt_s: float, spectral_density: float, axes: int = 3) -> FloatArray:
    """Discrete process noise of position and velocity driven by white acceleration.

    Per axis, over ``dt_s`` with acceleration noise of ``spectral_density`` ((m/s^2)^2/Hz):
    ``[[dt^3/3, dt^2/2], [dt^2/2, dt]] * spectral_density``. The result is ordered positions
    first, then velocities (``[p_x, p_y, p_z, v_x, v_y, v_z]`` for three axes), the layout of
    the filter's first six error states.
    """
    dt = float(dt_s)
    pp = dt**3 / 3.0 * spectral_density
    pv = dt**2 / 2.0 * spectral_density
    vv = dt * spectral_density
    q = np.zeros((2 * axes, 2 * axes))
    for i in range(axes):
        q[i, i] = pp
        q[i, axes + i] = q[axes + i, i] = pv
        q[axes + i, axes + i] = vv
    return q
