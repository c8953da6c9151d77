"""State estimation numerics: 6-D attitude filter and GPS/INS error-state Kalman filter.

Pure math with no threads or I/O; the estimator thread wraps these. Conventions throughout:
NED navigation frame, body x forward / y right / z down, quaternions (w, x, y, z) rotating
body vectors into NED, specific force in m/s^2 (about (0, 0, -g) level and still), rates in
rad/s. See docs/estimation.md.

Names are imported lazily, so a tool that lists parameters or reads logs does not load the
filters it never runs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from companion.core.lazy import lazy_exports

if TYPE_CHECKING:
    from companion.estimation.attitude import AttitudeFilter, estimate_attitude
    from companion.estimation.eskf import Eskf
    from companion.estimation.eskf_state import EskfState, EstimatorFault, UpdateResult

_EXPORTS = {
    "AttitudeFilter": "companion.estimation.attitude",
    "estimate_attitude": "companion.estimation.attitude",
    "Eskf": "companion.estimation.eskf",
    "EskfState": "companion.estimation.eskf_state",
    "EstimatorFault": "companion.estimation.eskf_state",
    "UpdateResult": "companion.estimation.eskf_state",
}

__all__ = [
    "AttitudeFilter",
    "Eskf",
    "EskfState",
    "EstimatorFault",
    "UpdateResult",
    "estimate_attitude",
]


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
