"""Classical axis-image reader: a weighted line per channel, their common point, and each line's far end.

The baseline and fallback for the regression network: no training, exact on clean images, fragile on
broken or blobby ones (every lit pixel of a channel is taken to belong to its axis).
"""

from __future__ import annotations

import numpy as np

from axispose_core.axis_image import DEFAULT_LINE_WIDTH
from axispose_core.tbm.keypoints import AxisKeypoints, unreadable

MIN_PIXELS = 3
"""A channel with fewer lit pixels than this has no readable axis."""


def fit_axis_keypoints(image: np.ndarray, threshold: float = 0.5, line_width: float = DEFAULT_LINE_WIDTH) -> AxisKeypoints:
    """Read origin and endpoints from an HxWx3 axis image with values in [0,1].

    Per channel, the lit pixels' intensity-weighted principal axis gives the line; the origin is the
    least-squares meeting point of the three lines (weighted by how line-like each channel is); each endpoint
    is the lit pixel furthest from the origin along its line, moved back by what the rounded cap adds
    (half the line width, less the half pixel by which the furthest lit pixel centre falls short of it).
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"axis image must be HxWx3, got {img.shape}")
    if not np.all(np.isfinite(img)):
        return unreadable("axis image has non-finite pixels")
    h, w, _ = img.shape
    ys, xs = np.mgrid[0:h, 0:w]
    lines = []
    for c in range(3):
        mask = img[..., c] >= threshold
        if mask.sum() < MIN_PIXELS:
            return unreadable(f"channel {'XYZ'[c]} has no axis (fewer than {MIN_PIXELS} lit pixels)")
        p = np.column_stack([xs[mask], ys[mask]]).astype(np.float64)
        wts = img[..., c][mask]
        mu = wts @ p / wts.sum()
        cov = ((p - mu) * wts[:, None]).T @ (p - mu) / wts.sum()
        evals, evecs = np.linalg.eigh(cov)
        elong = max(evals[1] - evals[0], 0.0) / max(evals[1], 1e-12)
        lines.append((mu, evecs[:, 1], p, elong * np.sqrt(max(evals[1], 0.0))))
    A = np.zeros((2, 2))
    b = np.zeros(2)
    for mu, d, _, weight in lines:
        P = np.eye(2) - np.outer(d, d)
        A += weight * P
        b += weight * P @ mu
    if np.linalg.cond(A) > 1e8:
        return unreadable("axis lines are parallel: no common origin")
    origin = np.linalg.solve(A, b)
    ends = np.empty((3, 2))
    for c, (_, d, p, _) in enumerate(lines):
        s = (p - origin) @ d
        far = s.max() if abs(s.max()) >= abs(s.min()) else s.min()
        # The 0.5 threshold sits w/2 beyond the endpoint; the furthest lit pixel centre lies on average
        # half a pixel inside that boundary.
        reach = max(abs(far) - (0.5 * line_width - 0.5), 0.0)
        ends[c] = origin + np.sign(far) * reach * d
    return AxisKeypoints(origin, ends)
