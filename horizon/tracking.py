"""Temporal tracking for video: a prediction from past frames that helps, but never overrules,
the single-frame detector.

The thesis tried predicting the horizon from the previous result and found it useless because
there was no way to tell how far to trust either the past or the present result. Here both carry
a number: each detection has a quality, and the track has a confidence that rises while
detections agree with the prediction and falls when they are missing or disagree. The prediction
only adds a candidate and a bonus for candidates near it, scaled by that confidence; when the
confidence runs out the detector is back to pure single-frame operation. A detection that jumps
away from a confident track is still reported (the jump may be real) but with a lowered quality,
so the estimator can weigh it.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from horizon.camera import CameraModel
from horizon.estimate import HorizonEstimate
from horizon.geometry import OrientedLine, wrap_deg
from horizon.robust import Prior, RobustDetector

__all__ = ["HorizonTracker"]

MIN_CONFIDENCE = 0.15
MISS_DECAY = 0.75
JUMP_DECAY = 0.6
AGREE_CLOSENESS = 0.3
ROLL_SCALE_DEG = 6.0
OFFSET_SCALE_FRAC = 0.06


class HorizonTracker:
    """Feed frames in order with :meth:`update`; call :meth:`reset` after a cut in the video."""

    def __init__(self, detector: RobustDetector | None = None, camera: CameraModel | None = None) -> None:
        self.detector = detector if detector is not None else RobustDetector(camera)
        self.confidence = 0.0
        self._roll_deg = 0.0
        self._offset = 0.0
        self._v_roll = 0.0
        self._v_offset = 0.0
        self._size: tuple[int, int] | None = None

    def reset(self) -> None:
        self.confidence = 0.0
        self._v_roll = self._v_offset = 0.0
        self._size = None

    def predicted_line(self) -> OrientedLine | None:
        """Where the horizon should be in the next frame, if the track is alive."""
        if self._size is None or self.confidence < MIN_CONFIDENCE:
            return None
        return OrientedLine.from_roll_offset(
            self._roll_deg + self._v_roll, self._offset + self._v_offset, *self._size
        )

    def update(self, frame: NDArray[np.uint8]) -> HorizonEstimate:
        h, w = frame.shape[:2]
        if self._size is not None and self._size != (w, h):
            self.reset()
        predicted = self.predicted_line()
        prior = Prior(predicted, self.confidence) if predicted is not None else None
        est = self.detector.detect(frame, prior)

        if not est.found or est.roll_deg is None or est.offset_frac is None:
            self.confidence *= MISS_DECAY
            return est

        if predicted is None:
            self._start(est, w, h)
            return est

        agreement = self._agreement(est, predicted)
        if agreement >= AGREE_CLOSENESS:
            d_roll = wrap_deg(est.roll_deg - self._roll_deg)
            d_off = est.offset_frac - self._offset
            self._v_roll = 0.5 * self._v_roll + 0.5 * d_roll
            self._v_offset = 0.5 * self._v_offset + 0.5 * d_off
            self._roll_deg, self._offset = est.roll_deg, est.offset_frac
            self.confidence = min(1.0, 0.6 * self.confidence + 0.4 * est.quality + 0.1 * agreement)
            return est
        # a jump: believe it if the detection is surer than the track is
        trust_track = self.confidence
        if est.quality >= trust_track:
            self._start(est, w, h)
        else:
            self.confidence *= JUMP_DECAY
        lowered = est.quality * (1.0 - 0.5 * trust_track)
        return replace(est, quality=lowered)

    def _start(self, est: HorizonEstimate, w: int, h: int) -> None:
        assert est.roll_deg is not None and est.offset_frac is not None
        self._size = (w, h)
        self._roll_deg, self._offset = est.roll_deg, est.offset_frac
        self._v_roll = self._v_offset = 0.0
        self.confidence = 0.5 * est.quality

    def _agreement(self, est: HorizonEstimate, predicted: OrientedLine) -> float:
        assert est.roll_deg is not None and est.offset_frac is not None
        d_roll = wrap_deg(est.roll_deg - predicted.roll_deg)
        d_off = est.offset_frac - predicted.offset_frac
        if math.isnan(d_off):
            return 0.0
        return math.exp(-((d_roll / ROLL_SCALE_DEG) ** 2) - (d_off / OFFSET_SCALE_FRAC) ** 2)
