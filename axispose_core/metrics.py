"""Pose errors as pure functions, in the style of bop_toolkit's ``pose_error.py``.

Poses are model-to-camera (R 3x3, t (3,) in metres); `pts` are model points (N,3) in metres; K is 3x3.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from axispose_core.camera import project, transform


def add(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, pts: np.ndarray) -> float:
    """ADD: mean distance (m) between model points under the estimated and the true pose."""
    return float(np.linalg.norm(transform(R_est, t_est, pts) - transform(R_gt, t_gt, pts), axis=1).mean())


def adi(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, pts: np.ndarray) -> float:
    """ADD-S (ADI): mean distance (m) from each estimated model point to the nearest true one; for symmetric objects."""
    est = transform(R_est, t_est, pts)
    dist, _ = cKDTree(transform(R_gt, t_gt, pts)).query(est, k=1)
    return float(dist.mean())


def proj(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, K: np.ndarray, pts: np.ndarray) -> float:
    """Mean 2D reprojection error (px) of the model points."""
    return float(np.linalg.norm(project(K, transform(R_est, t_est, pts)) - project(K, transform(R_gt, t_gt, pts)), axis=1).mean())


def re(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Rotation error (degrees): the angle of R_est R_gtᵀ (atan2 form, accurate for tiny angles too)."""
    D = np.asarray(R_est) @ np.asarray(R_gt).T
    sin = 0.5 * np.linalg.norm([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]])
    cos = 0.5 * (np.trace(D) - 1.0)
    return float(np.degrees(np.arctan2(sin, cos)))


def te(t_est: np.ndarray, t_gt: np.ndarray) -> float:
    """Translation error (m): Euclidean distance of the translations."""
    return float(np.linalg.norm(np.asarray(t_est) - np.asarray(t_gt)))


def add_or_adi(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, pts: np.ndarray, symmetric: bool) -> float:
    """ADD(-S): ADI for symmetric objects, ADD otherwise (the LM-O convention)."""
    return (adi if symmetric else add)(R_est, t_est, R_gt, t_gt, pts)


ADD_THRESHOLDS = (0.1, 0.2)
"""Fractions of the object diameter at which ADD(-S) counts a pose as correct."""
REPROJ_THRESHOLDS = (5.0, 15.0)
"""Pixel thresholds at which the mean reprojection error counts a pose as correct."""


def pose_scores(
    R_est: np.ndarray,
    t_est: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
    K: np.ndarray,
    pts: np.ndarray,
    diameter: float,
    symmetric: bool,
) -> dict[str, float]:
    """Every error and thresholded success used in reports, keyed as in the eval JSON (add_0.1d, reproj_5px, ...)."""
    add_err = add_or_adi(R_est, t_est, R_gt, t_gt, pts, symmetric)
    proj_err = proj(R_est, t_est, R_gt, t_gt, K, pts)
    scores: dict[str, float] = {"add_err_m": add_err, "reproj_err_px": proj_err}
    for frac in ADD_THRESHOLDS:
        scores[f"add_{frac:g}d"] = float(add_err < frac * diameter)
    for px in REPROJ_THRESHOLDS:
        scores[f"reproj_{px:g}px"] = float(proj_err < px)
    scores["rot_err_deg"] = re(R_est, R_gt)
    scores["trans_err_mm"] = 1000.0 * te(t_est, t_gt)
    return scores
