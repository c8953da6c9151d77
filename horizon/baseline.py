"""The thesis's 2003 detector, kept faithful as the reference the other methods are judged by.

Pipeline (thesis chapter 6.2.2): a 3x3 derivative filter over the grey frame, a fixed threshold
that turns the response into a list of edge points, radial-distortion correction applied to those
points only, a Hough transform with trigonometric look-up tables in which every point votes for
every angle, and the global maximum of the accumulator as the horizon. It knows nothing about which
side is sky, so it reports the side above the line as sky (roll within +-90 deg).

Its known failures are the reason the robust method exists: noise passes the filter as filled
blobs, sync stripes out-vote the horizon, and nearer roads or buildings give longer alignments.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

from horizon.camera import CameraModel
from horizon.estimate import HorizonEstimate
from horizon.geometry import OrientedLine
from horizon.hough import HoughSpace, global_maximum, vote_all_angles

__all__ = ["BaselineDetector"]

# |gx| + |gy| of the 3x3 Sobel pair on 0..255 grey, so a clean step of about 30 grey levels passes
DEFAULT_THRESHOLD = 120
# frames are first reduced to this size (longer side), standing in for the thesis's low-resolution
# analogue capture: at full resolution a 3x3 filter sees ground texture long before the horizon
PROCESS_SIDE_PX = 160
# fraction of the line's length inside the image that must be edge points to call it a horizon
MIN_SUPPORT = 0.15


class BaselineDetector:
    """Stateless thesis pipeline; one instance can serve any frame size."""

    name = "baseline"

    def __init__(
        self,
        camera: CameraModel | None = None,
        threshold: int = DEFAULT_THRESHOLD,
        n_theta: int = 180,
        process_side_px: int = PROCESS_SIDE_PX,
    ) -> None:
        self.camera = camera
        self.threshold = threshold
        self.n_theta = n_theta
        self.process_side_px = process_side_px
        self._spaces: dict[tuple[int, int], HoughSpace] = {}

    def edge_points(self, frame: NDArray[np.uint8]) -> NDArray[np.float64]:
        """Pixels whose 3x3 derivative response passes the fixed threshold, as an N x 2 list."""
        grey = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        gx = cv2.Sobel(grey, cv2.CV_16S, 1, 0, ksize=3)
        gy = cv2.Sobel(grey, cv2.CV_16S, 0, 1, ksize=3)
        mag = cv2.add(cv2.convertScaleAbs(gx, alpha=0.25), cv2.convertScaleAbs(gy, alpha=0.25))
        # the scaled sum saturates at 255; compare in the same units
        ys, xs = np.nonzero(mag >= self.threshold / 4.0)
        return np.column_stack([xs, ys]).astype(np.float64)

    def detect(self, frame: NDArray[np.uint8]) -> HorizonEstimate:
        full_h, full_w = frame.shape[:2]
        scale = min(1.0, self.process_side_px / max(full_w, full_h))
        if scale < 1.0:
            size = (max(8, round(full_w * scale)), max(8, round(full_h * scale)))
            frame = np.asarray(cv2.resize(frame, size, interpolation=cv2.INTER_AREA), np.uint8)
        h, w = frame.shape[:2]
        camera = self.camera.scaled_to(w, h) if self.camera is not None else None
        pts = self.edge_points(frame)
        if camera is not None and len(pts):
            pts = camera.undistort_points(pts)
        space = self._spaces.get((w, h))
        if space is None:
            if len(self._spaces) >= 16:
                self._spaces.clear()
            space = HoughSpace(w, h, self.n_theta, 1.0)
            self._spaces[(w, h)] = space
        acc = vote_all_angles(space, pts)
        peak = global_maximum(space, acc)
        if peak is None:
            return HorizonEstimate.none(self.name, full_w, full_h)
        line = OrientedLine(math.degrees(peak.theta_rad), peak.rho_px, w, h)
        ends = line.border_points()
        if ends is None:
            return HorizonEstimate.none(self.name, full_w, full_h)
        length = math.dist(ends[0], ends[1])
        support = peak.votes / max(length, 1.0)
        if support < MIN_SUPPORT:
            return HorizonEstimate.none(self.name, full_w, full_h, support)
        full_cam = self.camera.scaled_to(full_w, full_h) if self.camera is not None else None
        return HorizonEstimate.from_line(
            line.scaled(full_w, full_h), min(support, 1.0), self.name, full_cam
        )
