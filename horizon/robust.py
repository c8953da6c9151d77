"""The project's best single-frame detector: the thesis's pipeline with its own proposed fixes.

1. Work on a copy reduced by a whole factor (area averaging already halves most transmission
   noise, and is cheap only at whole ratios).
2. Find sync-stripe rows (:mod:`horizon.stripes`), paint them over for the edge filter and keep
   them out of the statistics and the refinement.
3. Edge weights from the structure tensor: gradient strength times orientation coherence, so the
   filled, incoherent blobs that noise leaves in an edge map weigh almost nothing (the thesis's
   "filter out the internal points").
4. Hough transform in which each point votes only near its own gradient direction (fast, O(N)),
   then several local maxima instead of the global one, plus lines parallel to the strongest
   ones, since a weak horizon beside a strong parallel road may not make a peak of its own.
5. Each candidate is checked with sky/ground statistics over colour and texture (Wilks
   criterion, :mod:`horizon.skyground`); the best split wins, helped a little by its edge votes.
6. The winner is oriented (the brighter side is sky) and refined to sub-pixel precision on a strip
   of the full frame (:mod:`horizon.refine`).
7. Quality combines separation, the share of the line confirmed by an edge, and the sky/ground
   brightness contrast; below a threshold the answer is "no horizon".
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

from horizon.camera import CameraModel
from horizon.estimate import HorizonEstimate
from horizon.geometry import OrientedLine
from horizon.hough import HoughSpace, find_peaks, support_of, vote_oriented
from horizon.refine import refine_line
from horizon.skyground import SkyGroundStats
from horizon.stripes import inpaint_rows, stripe_rows

__all__ = ["RobustDetector", "Prior"]

WORK_SIDE_PX = 120  # the work copy's longer side is at most this
STATS_SIDE_PX = 40  # and the statistics copy's about this
REFINE_SIDE_PX = 320  # refinement samples the frame at about this resolution
MAX_EDGE_POINTS = 700
N_PEAKS = 8
PEAK_MIN_FRACTION = 0.05
N_PARALLEL_ANGLES = 2
PARALLEL_STEP_PX = 3.0  # in work pixels
SUPPORT_EXPONENT = 0.3
MIN_SIDE_SHARE = 0.02
PRIOR_GAIN = 1.0
PRIOR_RELAX = 0.6  # how far a confident, agreeing track lowers the acceptance threshold
UNCONFIRMED_SUPPORT = 0.25
FIT_TOLERANCE = 0.02  # of the height: steps this close count fully in the final fit
FULL_CONTRAST = 0.15
SEPARATION_ZERO = 0.3  # real horizons separate at 0.6..0.97, ground-only frames mostly below 0.5
SEPARATION_FULL = 0.8
MIN_QUALITY = 0.35


class Prior:
    """Where a tracker expects the horizon (a full-frame line), and how much it trusts that."""

    def __init__(self, line: OrientedLine, confidence: float) -> None:
        self.line = line
        self.confidence = float(min(max(confidence, 0.0), 1.0))


class _Grid:
    """A frame reduced ``k`` times, keeping its top-left origin: lines keep their normal and
    only their distance from the centre changes."""

    def __init__(self, width: int, height: int, k: int) -> None:
        self.k = k
        self.src_w, self.src_h = width, height
        self.w, self.h = max(1, width // k), max(1, height // k)
        # where this grid's centre lands in source pixels, relative to the source centre
        self.dx = k * (self.w - 1) / 2.0 + (k - 1) / 2.0 - (width - 1) / 2.0
        self.dy = k * (self.h - 1) / 2.0 + (k - 1) / 2.0 - (height - 1) / 2.0

    def reduce(self, img: NDArray[np.uint8]) -> NDArray[np.uint8]:
        if self.k == 1:
            return img
        crop = img[: self.h * self.k, : self.w * self.k]
        return np.asarray(cv2.resize(crop, (self.w, self.h), interpolation=cv2.INTER_AREA), np.uint8)

    def reduce_float(self, img: NDArray[np.float32]) -> NDArray[np.float32]:
        if self.k == 1:
            return img
        crop = img[: self.h * self.k, : self.w * self.k]
        return np.asarray(cv2.resize(crop, (self.w, self.h), interpolation=cv2.INTER_AREA), np.float32)

    def rho_down(self, t: NDArray[np.float64], rho: NDArray[np.float64]) -> NDArray[np.float64]:
        return (rho - np.cos(t) * self.dx - np.sin(t) * self.dy) / self.k

    def rho_up(self, t: float, rho: float) -> float:
        return self.k * rho + math.cos(t) * self.dx + math.sin(t) * self.dy


class RobustDetector:
    """Hough candidates verified by sky/ground statistics, then refined. Stateless between
    frames; :class:`horizon.tracking.HorizonTracker` adds temporal memory through ``prior``.

    ``diagnostics`` holds the last frame's intermediate figures, for tuning and benchmarks.
    """

    name = "robust"

    def __init__(self, camera: CameraModel | None = None) -> None:
        self.camera = camera
        self._spaces: dict[tuple[int, int], HoughSpace] = {}
        self.diagnostics: dict[str, float] = {}

    def detect(self, frame: NDArray[np.uint8], prior: Prior | None = None) -> HorizonEstimate:
        if frame.ndim == 2:
            frame = np.asarray(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR), np.uint8)
        h, w = frame.shape[:2]
        self.diagnostics = {}
        camera = self.camera.scaled_to(w, h) if self.camera is not None else None

        # 1-2. work copy and sync stripes
        work = _Grid(w, h, max(1, math.ceil(max(w, h) / WORK_SIDE_PX)))
        small = work.reduce(frame)
        grey = np.asarray(cv2.cvtColor(small, cv2.COLOR_BGR2GRAY), np.uint8)
        bad_small = stripe_rows(grey)
        if bad_small.any():
            grey = inpaint_rows(grey, bad_small)

        # 3-4. coherent edge points, oriented Hough, candidate lines (work pixels)
        pts, normals, weights, mag = _edge_points(grey, bad_small)
        if camera is not None and camera.has_distortion and len(pts):
            # distortion is corrected on the points only, in full-frame pixels
            k = work.k
            und = camera.undistort_points((pts + 0.5) * k - 0.5)
            pts = (und + 0.5) / k - 0.5
        space = self._space(work.w, work.h)
        acc = vote_oriented(space, pts, normals, weights)
        peaks = find_peaks(space, acc, N_PEAKS, min_fraction=PEAK_MIN_FRACTION)
        cand_t = [p.theta_rad for p in peaks]
        cand_r = [p.rho_px for p in peaks]
        for p in peaks[:N_PARALLEL_ANGLES]:
            reach = 0.5 * (work.w - 1) * abs(math.cos(p.theta_rad)) + 0.5 * (work.h - 1) * abs(
                math.sin(p.theta_rad)
            )
            n = int(reach // PARALLEL_STEP_PX)
            cand_t.extend([p.theta_rad] * (2 * n + 1))
            cand_r.extend(PARALLEL_STEP_PX * np.arange(-n, n + 1))
        use_prior = prior is not None and prior.confidence > 0
        if prior is not None and use_prior:
            pt = math.radians(prior.line.normal_deg)
            full_rho = prior.line.rebased(w, h).rho_px
            cand_t.append(pt)
            cand_r.append(float(work.rho_down(np.array([pt]), np.array([full_rho]))[0]))
        if not cand_t:
            return HorizonEstimate.none(self.name, w, h)
        theta = np.array(cand_t, np.float64)
        rho = np.array(cand_r, np.float64)
        votes = support_of(space, acc, theta, rho)

        # 5. sky/ground statistics on a still smaller copy
        stats_grid = _Grid(work.w, work.h, max(1, round(max(work.w, work.h) / STATS_SIDE_PX)))
        tiny = stats_grid.reduce(small)
        k2, th, tw = stats_grid.k, stats_grid.h, stats_grid.w
        row_ok = 1.0 - bad_small[: th * k2].reshape(th, k2).mean(axis=1)
        texture = stats_grid.reduce_float(mag)
        stats = SkyGroundStats(tiny, np.repeat(row_ok[:, None], tw, axis=1), texture)
        sp = stats.evaluate(theta, stats_grid.rho_down(theta, rho))
        top = max(float(votes.max()), 1e-9)
        support = np.maximum(votes, 0.05 * top) / top
        share = np.minimum(sp.positive_share, 1.0 - sp.positive_share)
        score = np.where(share >= MIN_SIDE_SHARE, sp.separation * support**SUPPORT_EXPONENT, 0.0)
        if prior is not None and use_prior:
            score *= 1.0 + PRIOR_GAIN * prior.confidence * _closeness(
                theta, rho, theta[-1], rho[-1], work.h
            )
        best = int(np.argmax(score))
        if score[best] <= 0:
            return HorizonEstimate.none(self.name, w, h)

        # 6. orientation and refinement on the full frame
        t_best = float(theta[best])
        line = OrientedLine(math.degrees(t_best), work.rho_up(t_best, float(rho[best])), w, h)
        flipped = bool(sp.grey_pos[best] > sp.grey_neg[best])  # the brighter side is the sky
        fisher = sp.fisher_bgr[best]
        if flipped:
            line, fisher = line.flipped(), -fisher
        fisher = fisher / (np.linalg.norm(fisher) + 1e-12) / 255.0
        bad_full = np.repeat(bad_small, work.k)
        bad_full = np.concatenate([bad_full, np.full(h - len(bad_full), bad_full[-1])])
        step_px = max(1.0, max(w, h) / REFINE_SIDE_PX)
        # a line the statistics like but no edge confirms is kept at a lower quality
        confirmed = UNCONFIRMED_SUPPORT
        for half_px, tol_px in ((0.07 * h, 1.5 * step_px), (0.025 * h, FIT_TOLERANCE * h)):
            ref = refine_line(
                frame, line, fisher, half_px, camera, bad_full, step_px=step_px, tolerance_px=tol_px
            )
            if ref is None:
                break
            line, confirmed = ref.line, max(ref.inlier_frac, UNCONFIRMED_SUPPORT)

        # 7. quality
        sky, ground = (sp.grey_pos, sp.grey_neg) if flipped else (sp.grey_neg, sp.grey_pos)
        sky_grey, ground_grey = float(sky[best]), float(ground[best])
        # a sky no brighter than its ground is most often two kinds of ground (or two of sky)
        contrast = (sky_grey - ground_grey) / (sky_grey + ground_grey + 0.05)
        separation = float(sp.separation[best])
        quality = (
            _ramp(separation, SEPARATION_ZERO, SEPARATION_FULL)
            * math.sqrt(confirmed)
            * _ramp(contrast, 0.0, FULL_CONTRAST)
        )
        self.diagnostics = {
            "candidates": float(len(theta)),
            "separation": separation,
            "confirmed": confirmed,
            "contrast": contrast,
            "sky_grey": sky_grey,
            "ground_grey": ground_grey,
            "quality": quality,
        }
        threshold = MIN_QUALITY
        if prior is not None and use_prior:
            # a weak line where a confident track expects one is accepted (at its own low
            # quality): that is what the tracker's memory is for
            agree = float(
                _closeness(
                    np.array([math.radians(line.normal_deg)]),
                    np.array([line.rho_px]),
                    math.radians(prior.line.normal_deg),
                    prior.line.rebased(w, h).rho_px,
                    h,
                )[0]
            )
            threshold *= 1.0 - PRIOR_RELAX * prior.confidence * agree
            self.diagnostics["prior_agreement"] = agree
        if quality < threshold:
            return HorizonEstimate.none(self.name, w, h, quality)
        return HorizonEstimate.from_line(line, quality, self.name, camera)

    def _space(self, w: int, h: int) -> HoughSpace:
        space = self._spaces.get((w, h))
        if space is None:
            if len(self._spaces) >= 16:
                self._spaces.clear()
            space = HoughSpace(w, h, n_theta=90, rho_step_px=1.0)
            self._spaces[(w, h)] = space
        return space


def _ramp(x: float, zero: float, full: float) -> float:
    return min(max((x - zero) / (full - zero), 0.0), 1.0)


def _edge_points(
    grey: NDArray[np.uint8], bad_rows: NDArray[np.bool_]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float32]]:
    """Edge points, their gradient direction and a weight that favours long, straight, coherent
    edges over noise and texture; also the gradient magnitude image (the texture measure)."""
    g = grey.astype(np.float32)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    jxx = cv2.boxFilter(gx * gx, -1, (5, 5))
    jyy = cv2.boxFilter(gy * gy, -1, (5, 5))
    jxy = cv2.boxFilter(gx * gy, -1, (5, 5))
    diff = jxx - jyy
    coherence = np.sqrt(diff * diff + 4.0 * jxy * jxy) / (jxx + jyy + 1e-6)
    mag = np.asarray(np.sqrt(gx * gx + gy * gy), np.float32)
    weight = mag * coherence * coherence
    if bad_rows.any():
        # the painted-over stripe rows carry only an interpolated ramp
        bad = bad_rows.copy()
        bad[1:] |= bad_rows[:-1]
        bad[:-1] |= bad_rows[1:]
        weight[bad, :] = 0.0
    # the frame border has no neighbours on one side: its response is not an edge
    weight[:1, :] = weight[-1:, :] = 0.0
    weight[:, :1] = weight[:, -1:] = 0.0
    flat = weight.ravel()
    k = min(MAX_EDGE_POINTS, flat.size)
    idx = np.argpartition(flat, flat.size - k)[flat.size - k :]
    top = float(flat[idx].max()) if k else 0.0
    idx = idx[flat[idx] > 0.05 * top]
    ys, xs = np.divmod(idx, grey.shape[1])
    orient = 0.5 * np.arctan2(2.0 * jxy.ravel()[idx], diff.ravel()[idx])
    pts = np.column_stack([xs, ys]).astype(np.float64)
    return pts, orient.astype(np.float64), flat[idx].astype(np.float64), mag


def _closeness(
    theta: NDArray[np.float64], rho: NDArray[np.float64], t0: float, r0: float, height: int
) -> NDArray[np.float64]:
    """1 for the line (t0, r0) itself, falling off over a few degrees and a few percent of the
    height; lines compare unoriented (a normal and its opposite are the same line)."""
    d = np.mod(theta - t0 + math.pi, 2.0 * math.pi) - math.pi
    same = np.abs(d) < math.pi / 2
    d_ang = np.degrees(np.where(same, d, np.mod(d, math.pi) - np.where(d > 0, math.pi, 0.0)))
    d_rho = np.abs(np.where(same, rho - r0, rho + r0)) / height
    return np.exp(-((d_ang / 5.0) ** 2) - (d_rho / 0.05) ** 2)
