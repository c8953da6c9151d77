"""Hough transforms over an edge-point list, and peak picking in the accumulator.

Lines are ``x cos(t) + y sin(t) = rho`` with ``(x, y)`` relative to the image centre and ``t`` in
[0, pi), so the normal points downward (or right, for a vertical line): read as a horizon, the sky
is on the upper side. Both transforms look their sines and cosines up in a table made once per
accumulator shape, as the thesis did.

Two voting schemes:

* :func:`vote_all_angles` is the thesis's: every point votes once for every angle, O(N * T).
* :func:`vote_oriented` lets a point vote only near the angle its gradient points to, with a weight
  (O'Gorman and Clowes' use of edge direction): O(N * w) with w a handful of bins, and random noise,
  whose gradients point anywhere, spreads its votes thin instead of building false peaks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = [
    "HoughSpace",
    "HoughPeak",
    "vote_all_angles",
    "vote_oriented",
    "find_peaks",
    "global_maximum",
    "support_of",
]

# points per chunk in the all-angles vote, so memory stays bounded whatever the edge count
_CHUNK_POINTS = 4096


@dataclass(frozen=True)
class HoughSpace:
    """Accumulator geometry for one image size: ``n_theta`` angle bins over [0, pi) and rho bins
    of ``rho_step_px`` covering the half-diagonal both ways."""

    width: int
    height: int
    n_theta: int = 180
    rho_step_px: float = 1.0
    cos_t: NDArray[np.float64] = field(init=False, repr=False, compare=False)
    sin_t: NDArray[np.float64] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        cos_t, sin_t = _trig_tables(self.n_theta)
        object.__setattr__(self, "cos_t", cos_t)
        object.__setattr__(self, "sin_t", sin_t)

    @property
    def rho_max_px(self) -> float:
        # a whole number of steps, so bin r and bin n_rho - 1 - r hold opposite distances
        half_bins = math.ceil((0.5 * math.hypot(self.width, self.height) + 1.0) / self.rho_step_px)
        return half_bins * self.rho_step_px

    @property
    def n_rho(self) -> int:
        return int(round(2.0 * self.rho_max_px / self.rho_step_px)) + 1

    @property
    def theta_step_rad(self) -> float:
        return math.pi / self.n_theta

    def theta_rad(self, t_index: float) -> float:
        return t_index * self.theta_step_rad

    def rho_px(self, r_index: float) -> float:
        return r_index * self.rho_step_px - self.rho_max_px

    def centred(self, pts_px: NDArray[np.floating]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        x = np.asarray(pts_px[:, 0], dtype=np.float64) - (self.width - 1) / 2.0
        y = np.asarray(pts_px[:, 1], dtype=np.float64) - (self.height - 1) / 2.0
        return x, y


@lru_cache(maxsize=16)
def _trig_tables(n_theta: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    t = np.arange(n_theta) * (math.pi / n_theta)
    cos_t, sin_t = np.cos(t), np.sin(t)
    cos_t.flags.writeable = False
    sin_t.flags.writeable = False
    return cos_t, sin_t


@dataclass(frozen=True)
class HoughPeak:
    """One accumulator peak: line angle and distance from the image centre, and its votes."""

    theta_rad: float
    rho_px: float
    votes: float


def vote_all_angles(space: HoughSpace, pts_px: NDArray[np.floating]) -> NDArray[np.int32]:
    """The thesis's transform: each point adds one vote to every angle's rho bin."""
    acc = np.zeros(space.n_rho * space.n_theta, dtype=np.int64)
    if len(pts_px) == 0:
        return acc.reshape(space.n_rho, space.n_theta).astype(np.int32)
    x, y = space.centred(pts_px)
    t_idx = np.arange(space.n_theta)
    inv_step = 1.0 / space.rho_step_px
    for start in range(0, len(x), _CHUNK_POINTS):
        xs = x[start : start + _CHUNK_POINTS, None]
        ys = y[start : start + _CHUNK_POINTS, None]
        rho = xs * space.cos_t[None, :] + ys * space.sin_t[None, :]
        r_idx = np.rint((rho + space.rho_max_px) * inv_step).astype(np.int64)
        flat = r_idx * space.n_theta + t_idx[None, :]
        # points outside the image (after distortion correction) may vote for lines that miss it
        inside = (r_idx >= 0) & (r_idx < space.n_rho)
        acc += np.bincount(flat[inside], minlength=acc.size)
    return acc.reshape(space.n_rho, space.n_theta).astype(np.int32)


def vote_oriented(
    space: HoughSpace,
    pts_px: NDArray[np.floating],
    normal_rad: NDArray[np.floating],
    weights: NDArray[np.floating],
    half_window_bins: int = 3,
) -> NDArray[np.float32]:
    """Weighted votes near each point's own normal angle (taken modulo pi).

    The vote tapers linearly across the window so a peak's angle is interpolated rather than
    flat-topped.
    """
    acc = np.zeros(space.n_rho * space.n_theta, dtype=np.float64)
    if len(pts_px) == 0:
        return acc.reshape(space.n_rho, space.n_theta).astype(np.float32)
    x, y = space.centred(pts_px)
    t0 = np.rint(np.mod(normal_rad, math.pi) / space.theta_step_rad).astype(np.int64)
    offsets = np.arange(-half_window_bins, half_window_bins + 1)
    taper = 1.0 - np.abs(offsets) / (half_window_bins + 1.0)
    t_raw = t0[:, None] + offsets[None, :]
    # crossing 0/pi flips the sign of rho for the same line
    wrapped = (t_raw < 0) | (t_raw >= space.n_theta)
    t_idx = np.mod(t_raw, space.n_theta)
    rho = x[:, None] * space.cos_t[t_idx] + y[:, None] * space.sin_t[t_idx]
    rho = np.where(wrapped, -rho, rho)
    r_idx = np.rint((rho + space.rho_max_px) / space.rho_step_px).astype(np.int64)
    flat = r_idx * space.n_theta + t_idx
    w = np.asarray(weights, dtype=np.float64)[:, None] * taper[None, :]
    inside = (r_idx >= 0) & (r_idx < space.n_rho)
    acc += np.bincount(flat[inside], weights=w[inside], minlength=acc.size)
    return acc.reshape(space.n_rho, space.n_theta).astype(np.float32)


def global_maximum(space: HoughSpace, acc: NDArray[np.number]) -> HoughPeak | None:
    """The single strongest cell, as the thesis selected its line."""
    if acc.size == 0:
        return None
    flat = int(np.argmax(acc))
    votes = float(acc.flat[flat])
    if votes <= 0:
        return None
    r, t = divmod(flat, space.n_theta)
    return HoughPeak(space.theta_rad(t), space.rho_px(r), votes)


def find_peaks(
    space: HoughSpace,
    acc: NDArray[np.float32],
    max_peaks: int,
    min_fraction: float = 0.15,
    neighbourhood: tuple[int, int] = (7, 9),
) -> list[HoughPeak]:
    """Up to ``max_peaks`` local maxima, strongest first, each refined to sub-bin precision.

    ``neighbourhood`` (rho bins, theta bins) is the non-maximum suppression window; peaks below
    ``min_fraction`` of the strongest are dropped. The angle axis is treated as circular (with
    the rho flip) so a near-vertical line does not produce two peaks.
    """
    if acc.size == 0 or max_peaks <= 0:
        return []
    pad = neighbourhood[1] // 2 + 1
    # circular extension in theta: column t + n_theta is column t with rho mirrored
    left = acc[::-1, -pad:]
    right = acc[::-1, :pad]
    ext = np.hstack([left, acc, right])
    smooth = np.asarray(cv2.GaussianBlur(ext, (3, 3), 0), np.float32)
    dil = cv2.dilate(smooth, cv2.getStructuringElement(cv2.MORPH_RECT, neighbourhood[::-1]))
    core = smooth[:, pad:-pad]
    peak_mask = (core >= dil[:, pad:-pad]) & (core > 0)
    top = float(core.max())
    if top <= 0:
        return []
    peak_mask &= core >= min_fraction * top
    r_idx, t_idx = np.nonzero(peak_mask)
    if len(r_idx) == 0:
        return []
    vals = core[r_idx, t_idx]
    order = np.argsort(-vals)[: max_peaks * 3]
    peaks: list[HoughPeak] = []
    taken: list[tuple[int, int]] = []
    for i in order:
        r, t = int(r_idx[i]), int(t_idx[i])
        # plateaus give several equal maxima next to each other: keep one
        if any(abs(r - r0) <= 1 and abs(t - t0) <= 1 for r0, t0 in taken):
            continue
        taken.append((r, t))
        dr = _parabola_offset(smooth[max(r - 1, 0) : r + 2, t + pad]) if 0 < r < space.n_rho - 1 else 0.0
        dt = _parabola_offset(smooth[r, t + pad - 1 : t + pad + 2])
        peaks.append(
            HoughPeak(space.theta_rad(t + dt), space.rho_px(r + dr), float(core[r, t]))
        )
        if len(peaks) >= max_peaks:
            break
    return peaks


def support_of(
    space: HoughSpace,
    acc: NDArray[np.floating],
    normal_rad: NDArray[np.floating],
    rho_px: NDArray[np.floating],
) -> NDArray[np.float64]:
    """Votes for arbitrary lines (either normal orientation): the largest cell within one bin
    of each, so a line between bins is not under-counted."""
    t = np.mod(np.asarray(normal_rad, np.float64), 2.0 * math.pi)
    rho = np.asarray(rho_px, np.float64)
    upper = t >= math.pi
    t = np.where(upper, t - math.pi, t)
    rho = np.where(upper, -rho, rho)
    ti = np.rint(t / space.theta_step_rad).astype(np.int64) % space.n_theta
    ri = np.rint((rho + space.rho_max_px) / space.rho_step_px).astype(np.int64)
    near = cv2.dilate(np.asarray(acc, np.float32), np.ones((3, 3), np.uint8))
    inside = (ri >= 0) & (ri < space.n_rho)
    out = np.zeros(len(t))
    out[inside] = near[ri[inside], ti[inside]]
    return out


def _parabola_offset(v: NDArray[np.floating]) -> float:
    if len(v) != 3:
        return 0.0
    a, b, c = float(v[0]), float(v[1]), float(v[2])
    den = a - 2.0 * b + c
    if den >= 0:
        return 0.0
    return max(-0.5, min(0.5, 0.5 * (a - c) / den))
