"""How well a line splits a frame into two colour populations: the statistical check on Hough
candidates that the thesis proposed (after Ettinger et al. 2002 and Todorovic et al. 2003).

Ettinger et al. scored a line by the colour covariances of the two regions it makes. Here the
score is the two-class Wilks criterion ``1 - det(S_within) / det(S_total)`` over the pixels' BGR
values: 0 when the line separates nothing, towards 1 when each side is one tight colour cluster.
A determinant ratio is unchanged by any invertible linear map of the colours, so exposure gain,
white-balance drift and colour casts do not move the score, which is what the thesis's failures
under colour alterations asked for.

All candidates are scored at once from per-pixel moments on a small image: each candidate costs a
mask and one matrix product.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["SkyGroundStats", "Splits"]


@dataclass(frozen=True)
class Splits:
    """Statistics of a batch of candidate lines, one entry per line: the separation score, the
    share of (weighted) pixels on the normal's positive side, each side's mean brightness (0..1)
    and texture, and the Fisher direction (BGR, for 0..1 colours) that best tells the two sides
    apart, pointing from the negative to the positive side."""

    separation: NDArray[np.float64]
    positive_share: NDArray[np.float64]
    grey_neg: NDArray[np.float64]
    grey_pos: NDArray[np.float64]
    texture_neg: NDArray[np.float64]
    texture_pos: NDArray[np.float64]
    fisher_bgr: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.separation)


class SkyGroundStats:
    """Per-pixel feature moments of one small frame, ready to score many lines.

    ``image`` is a small BGR image; ``weights`` (same height/width, 0..1) removes pixels that
    must not count, such as sync-stripe rows. ``texture`` (same size, optional) is a local
    gradient strength, used as a fourth feature next to the colour: sky is smooth where ground
    is textured, which tells an over-exposed white sky from a white road (as in Todorovic et
    al., who added texture to colour). Line coordinates are in the pixels of ``image``.
    """

    def __init__(
        self,
        image: NDArray[np.uint8],
        weights: NDArray[np.floating] | None = None,
        texture: NDArray[np.floating] | None = None,
    ) -> None:
        h, w = image.shape[:2]
        self.width, self.height = w, h
        feats = [image.reshape(-1, 3).astype(np.float64) / 255.0]
        if texture is not None:
            feats.append(np.asarray(texture, np.float64).reshape(-1, 1) / 255.0)
        f = np.hstack(feats)
        self.dim = f.shape[1]
        wt = np.ones(h * w) if weights is None else np.asarray(weights, np.float64).reshape(-1)
        # centred features keep the single-precision moment sums free of cancellation
        self._offset = (f * wt[:, None]).sum(axis=0) / max(float(wt.sum()), 1e-9)
        f = f - self._offset[None, :]
        iu, ju = np.triu_indices(self.dim)
        self._iu, self._ju = iu, ju
        mom = np.hstack([np.ones((h * w, 1)), f, f[:, iu] * f[:, ju]]) * wt[:, None]
        self._mom = mom.astype(np.float32)
        self._total = mom.sum(axis=0)
        ys, xs = np.mgrid[0:h, 0:w]
        self._x = (xs.reshape(-1) - (w - 1) / 2.0).astype(np.float32)
        self._y = (ys.reshape(-1) - (h - 1) / 2.0).astype(np.float32)
        st = self._covariance(self._total[None, :])[0]
        # regularise with a small share of the total spread so flat or grey frames stay finite
        self._ridge = (1e-3 * float(np.trace(st)) / self.dim + 1e-6) * np.eye(self.dim)
        self._det_total = float(np.linalg.det(st + self._ridge))

    @property
    def total_weight(self) -> float:
        return float(self._total[0])

    def _covariance(self, m: NDArray[np.float64]) -> NDArray[np.float64]:
        """Feature covariances from rows of moments (count, sums, upper-triangle products)."""
        d = self.dim
        n = np.maximum(m[:, 0], 1e-9)
        mu = m[:, 1 : 1 + d] / n[:, None]
        e = np.empty((len(m), d, d))
        e[:, self._iu, self._ju] = m[:, 1 + d :]
        e[:, self._ju, self._iu] = m[:, 1 + d :]
        e /= n[:, None, None]
        return e - mu[:, :, None] * mu[:, None, :]

    def evaluate(self, normal_rad: NDArray[np.floating], rho_px: NDArray[np.floating]) -> Splits:
        """Score lines ``x cos t + y sin t = rho`` (centred coordinates of the small image).
        Pixels are shared between the sides by their area on each side, so the score varies
        smoothly as a line moves."""
        t = np.atleast_1d(np.asarray(normal_rad, np.float64))
        rho = np.atleast_1d(np.asarray(rho_px, np.float64))
        d = self.dim
        # share of each pixel on the positive side: its signed distance + 1/2, clipped to 0..1
        pos = np.outer(np.cos(t).astype(np.float32), self._x)
        pos += np.outer(np.sin(t).astype(np.float32), self._y)
        pos -= (rho - 0.5).astype(np.float32)[:, None]
        np.clip(pos, 0.0, 1.0, out=pos)
        m_pos = (pos @ self._mom).astype(np.float64)
        m_neg = self._total[None, :] - m_pos
        n_pos = np.maximum(m_pos[:, 0], 1e-9)
        n_neg = np.maximum(m_neg[:, 0], 1e-9)
        n_all = n_pos + n_neg
        within = (
            self._covariance(m_pos) * n_pos[:, None, None]
            + self._covariance(m_neg) * n_neg[:, None, None]
        ) / n_all[:, None, None] + self._ridge[None]
        det_w = np.linalg.det(within)
        sep = 1.0 - det_w / self._det_total if self._det_total > 0 else np.zeros_like(det_w)
        # a line that leaves one side (nearly) empty separates nothing
        sep = np.where(np.minimum(m_pos[:, 0], m_neg[:, 0]) < 1.0, 0.0, np.clip(sep, 0.0, 1.0))
        mean_pos = m_pos[:, 1 : 1 + d] / n_pos[:, None] + self._offset[None, :]
        mean_neg = m_neg[:, 1 : 1 + d] / n_neg[:, None] + self._offset[None, :]
        # the colour-only discriminant, for projecting frame pixels in the refinement
        fisher = np.linalg.solve(within[:, :3, :3], (mean_pos - mean_neg)[:, :3, None])[:, :, 0]
        no_tex = np.zeros(len(t))
        return Splits(
            separation=sep,
            positive_share=n_pos / n_all,
            grey_neg=mean_neg[:, :3].mean(axis=1),
            grey_pos=mean_pos[:, :3].mean(axis=1),
            texture_neg=mean_neg[:, 3] * 255.0 if d > 3 else no_tex,
            texture_pos=mean_pos[:, 3] * 255.0 if d > 3 else no_tex,
            fisher_bgr=fisher,
        )
