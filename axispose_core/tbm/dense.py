"""Translation from the encoder's dense surface points, given the rotation from the axes.

Each visible pixel u of the encoder's surface-point map says which model point X it shows; with R from the TBM,
u ≃ K (R X + t) is linear in t: (R X + t) × K⁻¹[u, 1] = 0 gives two equations per pixel. Hundreds of pixels
measure the object's image extent, hence its depth, more finely than one regressed scalar can, as far as the
points themselves are precise. No CAD model is needed: the points are the network's, in λ_O units.
"""

from __future__ import annotations

import numpy as np

MIN_POINTS = 8
"""Fewer usable correspondences than this give no translation."""


def translation_from_points(
    K: np.ndarray, R: np.ndarray, uv: np.ndarray, X: np.ndarray, weight: np.ndarray, iters: int = 20
) -> np.ndarray | None:
    """t (3,) such that model points X (N,3) seen at pixels uv (N,2) satisfy uv ≃ K (R X + t), by iteratively
    reweighted least squares: `weight` (N,) is each point's prior weight (e.g. the mask probability); robust
    weights on the residual, scaled by its median absolute deviation (Huber first, then Tukey's biweight, which
    gives points far off no weight at all), keep wrong points from pulling.
    None when fewer than MIN_POINTS have weight or the system is degenerate (all points on one ray)."""
    keep = weight > 0
    if keep.sum() < MIN_POINTS:
        return None
    uv, X, prior = uv[keep], X[keep], weight[keep].astype(np.float64)
    ray = np.linalg.solve(K, np.column_stack([uv, np.ones(len(uv))]).T).T  # (N,3): x, y, 1
    p = X @ R.T
    n = len(uv)
    A = np.zeros((2 * n, 3))
    A[:n, 0], A[:n, 2] = 1.0, -ray[:, 0]
    A[n:, 1], A[n:, 2] = 1.0, -ray[:, 1]
    b = np.concatenate([ray[:, 0] * p[:, 2] - p[:, 0], ray[:, 1] * p[:, 2] - p[:, 1]])
    w = np.concatenate([prior, prior])
    t = None
    for k in range(iters):
        sw = np.sqrt(w)
        sol, _, rank, _ = np.linalg.lstsq(A * sw[:, None], b * sw, rcond=None)
        if rank < 3:
            return None
        t = sol
        r = np.abs(A @ t - b)
        scale = 1.4826 * np.median(r) + 1e-12
        if k < 3:
            robust = np.minimum(1.0, 1.345 * scale / np.maximum(r, 1e-15))
        else:
            robust = np.clip(1 - (r / (4.685 * scale)) ** 2, 0, None) ** 2
        w = np.concatenate([prior, prior]) * robust
        if w.sum() <= 0:
            return None
    return t
