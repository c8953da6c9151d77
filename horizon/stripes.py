"""Finding the white or black bands that a lost vertical sync paints across a video frame.

A sync stripe is a run of whole rows at (nearly) peak white or black with almost no variation
along the row, with an abrupt change at both ends. Its two borders are the sharpest horizontal
lines in the frame, so the thesis's Hough maximum often chose one of them. A uniform sky touching
the top of the image also has flat bright rows; requiring an abrupt step at both ends of the run,
and that the run does not touch the top or bottom border, keeps such sky out.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["stripe_rows", "inpaint_rows"]

WHITE_MIN = 228.0
BLACK_MAX = 30.0
FLAT_STD_MAX = 8.0
LEVEL_SPREAD_MAX = 8.0
STEP_MIN = 25.0
TEXTURE_RATIO = 3.0
MAX_BAND_FRAC = 0.2
MAX_EDGE_BAND_FRAC = 0.08


def stripe_rows(grey: NDArray[np.uint8]) -> NDArray[np.bool_]:
    """Per-row flags: True for rows inside a sync stripe."""
    h = grey.shape[0]
    flags = np.zeros(h, bool)
    if h < 5:
        return flags
    mean = np.asarray(cv2.reduce(grey, 1, cv2.REDUCE_AVG, dtype=cv2.CV_32F)[:, 0], np.float32)
    sq = cv2.reduce(cv2.multiply(grey, grey, dtype=cv2.CV_32F), 1, cv2.REDUCE_AVG, dtype=cv2.CV_32F)
    sq = np.asarray(sq[:, 0], np.float32)
    std = np.sqrt(np.maximum(sq - mean * mean, 0.0))
    flat = (std <= FLAT_STD_MAX) & ((mean >= WHITE_MIN) | (mean <= BLACK_MAX))
    if not flat.any():
        return flags
    edges = np.flatnonzero(np.diff(np.concatenate([[0], flat.astype(np.int8), [0]])))
    for start, stop in zip(edges[::2], edges[1::2], strict=True):
        if _is_stripe(mean, std, int(start), int(stop), h):
            flags[start:stop] = True
    return flags


def _is_stripe(mean: NDArray[np.float32], std: NDArray[np.float32], start: int, stop: int, h: int) -> bool:
    """Whether the flat run ``[start, stop)`` is a painted band rather than flat sky or haze."""
    run = mean[start:stop]
    level = float(np.median(run))
    # a sliver of one row between band and border cannot be judged: treat it as the border
    near_top = start <= 1
    near_bottom = stop >= h - 1
    if near_top and (level > BLACK_MAX or near_bottom):
        return False  # flat white rows from the top are as likely an over-exposed sky
    if stop - start > (MAX_EDGE_BAND_FRAC if near_top or near_bottom else MAX_BAND_FRAC) * h:
        return False
    # painted at one level; rows blended with the scene by resampling may stray, a ramp does not
    if len(run) >= 3 and np.mean(np.abs(run - level) <= LEVEL_SPREAD_MAX) < 0.6:
        return False
    band_std = float(np.median(std[start:stop]))
    ends = ([] if near_top else [(max(0, start - 2), start)]) + (
        [] if near_bottom else [(stop, min(h, stop + 2))]
    )
    for lo, hi in ends:
        step = float(np.max(np.abs(mean[lo:hi] - level)))
        texture = float(np.max(std[lo:hi]))
        # the band must stand out from the scene at each end, by its level or by its flatness
        if step < STEP_MIN and texture < TEXTURE_RATIO * band_std + 4.0:
            return False
    return True


def inpaint_rows(grey: NDArray[np.uint8], flags: NDArray[np.bool_]) -> NDArray[np.uint8]:
    """A copy with the flagged rows, and the one blended row either side, replaced by a vertical
    linear blend of the nearest clean rows, so a derivative filter sees neither stripe border
    while an edge just outside the stripe keeps its strength."""
    h = grey.shape[0]
    bad = flags.copy()
    bad[1:] |= flags[:-1]
    bad[:-1] |= flags[1:]
    if not bad.any() or bad.all():
        return grey
    out = grey.astype(np.float32)
    good = np.flatnonzero(~bad)
    rows = np.flatnonzero(bad)
    above_idx = np.searchsorted(good, rows) - 1
    below_idx = above_idx + 1
    for r, ia, ib in zip(rows, above_idx, below_idx, strict=True):
        if ia < 0:
            out[r] = out[good[ib]]
        elif ib >= len(good):
            out[r] = out[good[ia]]
        else:
            a, b = good[ia], good[ib]
            t = (r - a) / (b - a)
            out[r] = (1 - t) * out[a] + t * out[b]
    _ = h
    return np.clip(out, 0, 255).astype(np.uint8)
