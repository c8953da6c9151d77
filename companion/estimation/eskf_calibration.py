"""The ESKF's calibration states: the gyro's matrix error and its bias's temperature coefficient.

Gyro matrix: a consumer gyro's sensitivity is good to a few per cent per axis and each axis
sees a per cent or two of the others. In a banked turn that is a rate error which comes and
goes with the turn, too quick for the bias states and, over a 20 s turn, a degree of tilt. Each
sample is corrected with the estimated ``(I + M)^-1``; the states learn through the attitude
errors the GPS sees, so only in turns and rolls (``gyro_matrix_std`` 0 leaves them out).

Temperature: the biases of a MEMS part follow its temperature by an unknown coefficient, and
the part warms by some 20 C after switch-on; ``set_temperature`` lets the bias covariance grow
with each measured temperature change (a random walk in temperature, not in time), so the
estimate keeps up with a warm-up and stays tight once the part is warm.

Separate from the navigation filter: these states belong to the part (a next flight can start
from what this one learnt, companion.estimation.calibration), with their own inputs (the IMU's
temperature) and setters.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import ArrayLike

from companion.core.mathutil import clamp
from companion.estimation.eskf_predict import Propagation
from companion.estimation.eskf_state import (
    IDX_ATT,
    IDX_GYRO_BIAS,
    IDX_GYRO_MATRIX,
    IDX_GYRO_TEMP,
    MAX_GYRO_TEMP_RAD_S_PER_C,
    TEMP_STEP_C,
)
from companion.estimation.quat import (
    FloatArray,
)

log = logging.getLogger(__name__)

class GyroCalibrationStates(Propagation):
    """The gyro matrix and temperature coefficient: inputs, setters and what was learnt."""

    def set_temperature(self, temperature_c: float) -> None:
        """The IMU's temperature (its slow block, about once a second).

        A MEMS part's biases follow its temperature with a coefficient no datasheet pins
        down (the MPU-6000's zero-rate output may move 20 deg/s between -40 and 85 C), so
        while the part warms up after switch-on its gyro bias can move a degree per second
        within minutes, far faster than a random walk tuned for a warm part allows. Each
        change of ``TEMP_STEP_C`` or more (quantisation and sensor noise stay below it) adds
        ``(coefficient^2) * TEMP_SPAN_C * |change|`` to the bias variances: a random walk in
        temperature rather than in time, whose spread over a warm-up of ``TEMP_SPAN_C``
        equals the coefficient's (for the gyro, ``GYRO_TEMP_RESIDUAL`` of it: what a straight
        line leaves). The gyro's bias also moves by its estimated coefficient times the
        change, and the change couples the bias error to the coefficient's, so the drift seen
        early in a warm-up is predicted later. A part at a steady temperature adds nothing.
        """
        try:
            t = float(temperature_c)
        except (TypeError, ValueError):
            self.rejected_inputs += 1
            return
        if not math.isfinite(t) or abs(t) > 200.0:
            self.rejected_inputs += 1
            return
        if not math.isfinite(self._temp_ref_c):
            self._temp_ref_c = t
            return
        change = t - self._temp_ref_c
        if abs(change) >= TEMP_STEP_C:
            self._pend_temp_c += abs(change)
            self._temp_ref_c = t
            if self._initialised and self.gyro_bias_temp_rad_s_per_c > 0.0:
                self._follow_temperature(change)

    def _follow_temperature(self, change_c: float) -> None:
        """Move the gyro bias by the estimated coefficient over a temperature change, and its
        error by the coefficient's error: b' = b + k dT, so d(b') = d(b) + dT d(k)."""
        self._propagate_covariance()  # the samples so far saw the bias as it was
        lim = self.max_gyro_bias_rad_s
        self._set_biases(np.array([clamp(self._bg_f[i] + k * change_c, -lim, lim)
                                   for i, k in enumerate(self._gyro_temp)]), self._ba)
        p = self._p
        b, k = IDX_GYRO_BIAS, IDX_GYRO_TEMP
        # P' = T P T' with T = I + dT (rows of b, columns of k), written out on the blocks
        p[b, :] += change_c * p[k, :]
        p[:, b] += change_c * p[:, k]

    @property
    def gyro_matrix_estimate(self) -> FloatArray:
        """The estimated scale-factor and cross-axis error ``M`` (3x3, a copy; zeros when it is
        not estimated): the gyro reads ``(I + M) w + b``."""
        return self._gm.copy()

    @property
    def gyro_temp_estimate_rad_s_per_c(self) -> tuple[float, float, float]:
        """The gyro bias's estimated temperature coefficient per axis (rad/s per degree C),
        without :meth:`state`'s copies (the flight thread logs it at every fix)."""
        return self._gyro_temp

    def gyro_calibration(self) -> tuple[list[float], list[float], list[float], list[float]]:
        """What the filter has learnt of the part: ``M`` (9, row-major), its 1-sigma per
        element, the temperature coefficient (3, rad/s/C) and its 1-sigma; a 1-sigma reads 0
        for what is not estimated. The flight thread logs it, and the next flight can start
        from it (`set_gyro_calibration`, companion.estimation.calibration)."""
        d = np.sqrt(np.maximum(np.diagonal(self._p), 0.0))
        m_std = d[IDX_GYRO_MATRIX].tolist() if self._gm_on else [0.0] * 9
        t_std = (d[IDX_GYRO_TEMP].tolist() if self.gyro_bias_temp_rad_s_per_c > 0.0
                 else [0.0] * 3)
        return self._gm.reshape(-1).tolist(), m_std, list(self._gyro_temp), t_std

    def gyro_matrix_diagonal(self) -> list[float]:
        """The scale-factor errors alone (the diagonal of :attr:`gyro_matrix_estimate`)."""
        return self._gm.diagonal().tolist()  # type: ignore[no-any-return]

    def set_gyro_matrix_std(self, std: float) -> bool:
        """Restart the gyro scale-factor and cross-axis estimate with a new prior (a parameter
        change): 0 stops estimating it and takes the gyro as exact again.

        False (and nothing changed) on a negative or non-finite value.
        """
        value = float(std)
        if not (math.isfinite(value) and value >= 0.0):
            self.rejected_inputs += 1
            return False
        self._propagate_covariance()
        self.gyro_matrix_std, self._gm_on = value, value > 0.0
        self._set_gm_apply()
        self._q_cache.clear()
        self._set_gyro_matrix(self._gm_prior.copy())
        self._pend_dth_f = (0.0, 0.0, 0.0)
        self._f[IDX_ATT, IDX_GYRO_MATRIX] = 0.0
        self._inflate(IDX_GYRO_MATRIX, self._gm_prior_var())
        return True

    def set_gyro_bias_temp(self, value: float) -> bool:
        """Change the gyro's temperature coefficient prior in flight (a parameter set): the
        coefficient restarts from zero with that 1-sigma (0: no coefficient, and the
        temperature no longer widens the gyro bias). False for a value that is not finite
        and >= 0."""
        if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0.0):
            self.rejected_inputs += 1
            return False
        self._propagate_covariance()
        self.gyro_bias_temp_rad_s_per_c = float(value)
        self._gyro_temp = self._gt_prior
        self._inflate(IDX_GYRO_TEMP, self._gt_prior_var())
        return True

    def set_gyro_calibration(self, matrix: ArrayLike, temp_rad_s_per_c: ArrayLike) -> bool:
        """Start the gyro's matrix error ``M`` and its bias's temperature coefficient from
        what a previous flight of this part learnt, instead of from zero.

        Both belong to the part and its mounting, not to one power-on, so what one flight
        learnt holds for the next. Without it every flight spends its first turns both ways
        relearning them, and a 20 s turn on a cross-axis error not yet seen is where the
        largest tilt errors fall: a rotation about the specific force is not observable in a
        steady turn, so the gyro's error about the body z axis goes straight into the tilt.
        ``gyro_matrix_std`` and ``gyro_bias_temp_rad_s_per_c`` stay the 1-sigma around these
        values; with ``gyro_matrix_std`` 0 the matrix is applied as exact. A running filter
        restarts both estimates from the new values.

        False (nothing changed) unless ``matrix`` is 3x3 (or 9 values, row-major) within
        ``max_gyro_matrix`` and ``temp_rad_s_per_c`` 3 values within
        ``MAX_GYRO_TEMP_RAD_S_PER_C``, all finite.
        """
        try:
            m = np.asarray(matrix, dtype=float).reshape(3, 3)
            k = np.asarray(temp_rad_s_per_c, dtype=float).reshape(3)
        except (TypeError, ValueError):
            self.rejected_inputs += 1
            return False
        if not (np.isfinite(m).all() and np.isfinite(k).all()
                and float(np.abs(m).max()) <= self.max_gyro_matrix * (1.0 + 1e-6)
                and float(np.abs(k).max()) <= MAX_GYRO_TEMP_RAD_S_PER_C * (1.0 + 1e-6)):
            # (the tolerance lets a float32 parameter at its range's end through)
            self.rejected_inputs += 1
            return False
        if self._initialised:
            self._propagate_covariance()
        self._gm_prior = m.copy()
        self._gt_prior = (float(k[0]), float(k[1]), float(k[2]))
        self._set_gm_apply()
        self._set_gyro_matrix(m.copy())
        self._gyro_temp = self._gt_prior
        self._pend_dth_f = (0.0, 0.0, 0.0)
        if self._initialised:
            self._inflate(IDX_GYRO_MATRIX, self._gm_prior_var())
            self._inflate(IDX_GYRO_TEMP, self._gt_prior_var())
        return True
