"""Sub-pixel refinement of a coarse horizon along a strip of the frame that follows it.

The strip is resampled so that its columns run across the line (sky at the top, ground at the
bottom) and its rows along it; the frame is projected onto the colour direction that best
separates sky from ground, each column's steepest sky-to-ground step is located with sub-pixel
interpolation, and a line is fitted through those steps with Tukey re-weighting so that columns
crossing a tree, a building or a cloud do not pull it. With a camera model the strip is sampled
through the lens distortion, so the fitted line is straight in undistorted coordinates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

from horizon.camera import CameraModel
from horizon.geometry import OrientedLine

__all__ = ["Refinement", "refine_line"]

# a step at least this fraction of the column's strongest, nearer the sky, is preferred: in haze
# the sky ends at the top of the haze band while the strongest step is the ground below it
SKYWARD_STEP_FRAC = 0.4


@dataclass(frozen=True)
class Refinement:
    """The refined line, the share of usable columns whose step agrees with it, and the RMS
    distance (pixels of the frame) of those steps from it."""

    line: OrientedLine
    inlier_frac: float
    rms_px: float
    step_strength: float


def refine_line(
    frame: NDArray[np.uint8],
    line: OrientedLine,
    fisher_bgr: NDArray[np.floating],
    half_width_px: float,
    camera: CameraModel | None = None,
    bad_rows: NDArray[np.bool_] | None = None,
    n_cols: int = 48,
    sub_samples: int = 6,
    step_px: float = 1.0,
    tolerance_px: float = 1.5,
) -> Refinement | None:
    """Fit the horizon near ``line`` in ``frame`` (both in the same pixel grid).

    ``fisher_bgr`` projects a BGR pixel (0..255) onto a scale that grows from sky to ground.
    ``bad_rows`` flags frame rows (distorted, i.e. as stored) that must not be used, such as
    sync stripes. ``step_px`` is the sample spacing across the line, so large frames cost no
    more than small ones. Steps within ``tolerance_px`` of the line keep full weight in the fit,
    so a gentle hill or tree line is averaged in the way a sky mask would include it. Returns
    None when too few columns show a step.
    """
    h, w = frame.shape[:2]
    ends = line.border_points()
    if ends is None:
        return None
    (x0, y0), (x1, y1) = ends
    length = math.hypot(x1 - x0, y1 - y0)
    if length < 8:
        return None
    dx, dy = (x1 - x0) / length, (y1 - y0) / length
    nx, ny = line.normal
    hw = max(3, int(math.ceil(half_width_px / step_px)))
    t = np.arange(-hw, hw + 1, dtype=np.float64) * step_px
    total_cols = n_cols * sub_samples
    margin = min(0.03 * length, 4.0)
    s = np.linspace(margin, length - margin, total_cols)
    px = x0 + s[None, :] * dx + t[:, None] * nx
    py = y0 + s[None, :] * dy + t[:, None] * ny
    if camera is not None and camera.has_distortion:
        pts = camera.distort_points(np.column_stack([px.ravel(), py.ravel()]))
        px = pts[:, 0].reshape(px.shape)
        py = pts[:, 1].reshape(py.shape)
    map_x = px.astype(np.float32)
    map_y = py.astype(np.float32)
    strip = cv2.remap(frame, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    proj = cv2.transform(strip.astype(np.float32), np.asarray(fisher_bgr, np.float32).reshape(1, 3))
    # average the sub-samples of each column (a whole-ratio area reduction), smooth across
    proj = cv2.resize(proj, (n_cols, len(t)), interpolation=cv2.INTER_AREA)
    proj = np.asarray(cv2.GaussianBlur(proj, (1, 3), 0), np.float64)

    # columns whose centre leaves the frame are not used; samples on bad rows are blanked
    mid = sub_samples // 2
    cx_col = map_x[hw, mid::sub_samples]
    cy_col = map_y[hw, mid::sub_samples]
    valid = (cx_col >= 0) & (cx_col <= w - 1) & (cy_col >= 0) & (cy_col <= h - 1)
    grad = proj[2:] - proj[:-2]  # at t[1:-1], sky-to-ground increase
    if bad_rows is not None and bad_rows.any():
        rows = np.clip(np.rint(map_y), 0, h - 1).astype(np.int64)
        bad = np.asarray(bad_rows[rows].reshape(len(t), n_cols, sub_samples).any(axis=2), bool)
        bad_g = bad[2:] | bad[1:-1] | bad[:-2]
        grad = np.where(bad_g, 0.0, grad)
        # a column that is mostly stripe has nothing to say
        valid &= bad_g.mean(axis=0) < 0.7
    cols = np.arange(n_cols)
    best = _first_strong_step(grad, SKYWARD_STEP_FRAC)
    peak = grad[best, cols]
    valid &= peak > 0
    if bad_rows is not None and bad_rows.any():
        # a step right next to a blanked stripe may be the stripe's border, not the horizon
        near = np.zeros(n_cols, bool)
        for k in range(-2, 3):
            idx = np.clip(best + k, 0, len(grad) - 1)
            near |= bad_g[idx, cols]
        valid &= ~near
    # sub-pixel vertex of the parabola through the peak and its neighbours
    lo = np.clip(best - 1, 0, len(grad) - 1)
    hi = np.clip(best + 1, 0, len(grad) - 1)
    a, b, c = grad[lo, cols], peak, grad[hi, cols]
    den = a - 2 * b + c
    frac = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
    frac = np.clip(frac, -0.5, 0.5)
    frac = np.where((best > 0) & (best < len(grad) - 1), frac, 0.0)
    offs = t[1:-1][best] + frac * step_px
    s_col = s.reshape(n_cols, sub_samples).mean(axis=1)

    n_valid = int(valid.sum())
    if n_valid < max(4, n_cols // 8):
        return None
    sv, ov, wv = s_col[valid], offs[valid], peak[valid]
    fit = _robust_line_fit(sv, ov, wv, tolerance_px)
    if fit is None:
        return None
    a0, slope, inlier, rms = fit
    s_mid = float(wv @ sv / wv.sum())
    # new line: through the fitted point at s_mid, direction turned by the fitted slope
    mx = x0 + s_mid * dx + (a0 + slope * 0.0) * nx
    my = y0 + s_mid * dy + (a0 + slope * 0.0) * ny
    ndx, ndy = dx + slope * nx, dy + slope * ny
    p1 = (mx - ndx * length, my - ndy * length)
    p2 = (mx + ndx * length, my + ndy * length)
    new_line = OrientedLine.from_points(p1, p2, line.width, line.height)
    strength = _median(wv[inlier]) if inlier.any() else 0.0
    return Refinement(new_line, float(inlier.sum()) / n_cols, rms, strength)


def _first_strong_step(grad: NDArray[np.floating], frac: float) -> NDArray[np.int64]:
    """Per column, the sky-most local maximum of ``grad`` that reaches ``frac`` of the column's
    maximum."""
    n = grad.shape[0]
    top = grad.max(axis=0)
    is_peak = np.ones_like(grad, dtype=bool)
    is_peak[1:] &= grad[1:] >= grad[:-1]
    is_peak[:-1] &= grad[:-1] >= grad[1:]
    strong = is_peak & (grad >= frac * top[None, :]) & (grad > 0)
    first = np.argmax(strong, axis=0)
    none = ~strong.any(axis=0)
    first[none] = np.argmax(grad, axis=0)[none]
    return np.minimum(first, n - 1).astype(np.int64)


def _robust_line_fit(
    s: NDArray[np.float64], o: NDArray[np.float64], w: NDArray[np.float64], min_scale: float
) -> tuple[float, float, NDArray[np.bool_], float] | None:
    """Weighted fit of ``o = a + slope * (s - s_mid)`` with Tukey biweights, started from the best
    of a few two-column hypotheses (a tiny RANSAC) so that a minority of far-off columns cannot
    drag the start."""
    s_mid = float(w @ s / w.sum())
    u = s - s_mid
    i_idx, j_idx = _pairs(len(s))
    base_w = w / (w.max() + 1e-12)
    du = u[j_idx] - u[i_idx]
    ok = du > 1e-9
    if ok.any():
        i_idx, j_idx, du = i_idx[ok], j_idx[ok], du[ok]
        b_h = (o[j_idx] - o[i_idx]) / du
        a_h = o[i_idx] - b_h * u[i_idx]
        resid = np.abs(o[None, :] - (a_h[:, None] + b_h[:, None] * u[None, :]))
        score = (resid < max(2.0, min_scale)) @ base_w
        k = int(np.argmax(score))
        a, b = float(a_h[k]), float(b_h[k])
    else:
        a, b = _median(o), 0.0
    c = 3.0
    for _ in range(4):
        r = o - (a + b * u)
        c = max(min_scale, 3.0 * 1.4826 * _median(np.abs(r)))
        z = r / c
        tw = np.where(np.abs(z) < 1.0, (1 - z * z) ** 2, 0.0) * w
        s0 = float(tw.sum())
        if s0 <= 0:
            return None
        s1, s2 = float(tw @ u), float(tw @ (u * u))
        t0, t1 = float(tw @ o), float(tw @ (u * o))
        det = s0 * s2 - s1 * s1
        if det <= 1e-12 * max(s0 * s2, 1e-12):
            return None
        a = (s2 * t0 - s1 * t1) / det
        b = (s0 * t1 - s1 * t0) / det
    r = o - (a + b * u)
    inlier = np.abs(r) < c
    rms = float(np.sqrt(np.mean(r[inlier] ** 2))) if inlier.any() else float("inf")
    return a, b, inlier, rms


@lru_cache(maxsize=64)
def _pairs(n: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Index pairs for the line hypotheses: about eight columns spread over the width, each
    paired with each other."""
    first = np.unique(np.linspace(0, n - 1, min(n, 9)).round().astype(np.int64))
    i_idx, j_idx = np.triu_indices(len(first), k=1)
    out_i, out_j = first[i_idx], first[j_idx]
    out_i.flags.writeable = False
    out_j.flags.writeable = False
    return out_i, out_j


def _median(v: NDArray[np.float64]) -> float:
    """Median of a short vector without numpy's general-purpose overhead (upper median)."""
    k = len(v) // 2
    return float(np.partition(v, k)[k])
