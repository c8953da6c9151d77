"""Small numeric helpers for the per-sample paths (drivers, simulator, control, estimator).

Why not ``min(max(x, lo), hi)``: at 100 Hz over a dozen values per tick it was a measurable
share of a lockstep flight; the two builtins cost about 160 ns together, this about 35 ns.
NaN passes through unchanged in both forms.
"""

from __future__ import annotations

import math
from typing import Any, TypeVar

__all__ = ["clamp", "wrap_pi"]

_Num = TypeVar("_Num", int, float)
_Angle = TypeVar("_Angle", bound=Any)


def clamp(x: _Num, lo: _Num, hi: _Num) -> _Num:
    """``x`` limited to ``lo..hi`` (ints stay ints)."""
    return lo if x < lo else hi if x > hi else x


def wrap_pi(angle_rad: _Angle) -> _Angle:
    """Angles wrapped into ``[-pi, pi)``: a float for a float (the control law, per step), an
    array for a numpy array (the estimator's innovations, the report's errors). One formula
    for both, so a scalar and the same value in an array wrap to the same bits."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi  # type: ignore[no-any-return]
