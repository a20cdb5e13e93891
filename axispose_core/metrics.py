"""Pose errors as pure functions, in the style of bop_toolkit's ``pose_error.py``.

Poses are model-to-camera (R 3x3, t (3,) in metres); `pts` are model points (N,3) in metres; K is 3x3.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

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


def mahalanobis_sq(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, covariance: np.ndarray) -> tuple[float, float]:
    """Squared Mahalanobis lengths of an estimate's translation error t_est - t_gt and rotation error (the
    rotation vector of R_est R_gtᵀ, camera frame) under its (6, 6) covariance in geometry_msgs' order (x, y, z,
    rotation about X, Y, Z): each is χ²(3)-distributed if the covariance is right and the error Gaussian."""
    e_t = np.asarray(t_est, dtype=float) - np.asarray(t_gt, dtype=float)
    e_r = Rotation.from_matrix(np.asarray(R_est) @ np.asarray(R_gt).T).as_rotvec()
    C = np.asarray(covariance, dtype=float)
    return float(e_t @ np.linalg.solve(C[:3, :3], e_t)), float(e_r @ np.linalg.solve(C[3:, 3:], e_r))


Symmetry = tuple[np.ndarray, np.ndarray]
"""(R, t): a model-frame transformation (t in metres) under which the object looks the same."""

FLIP_TOLERANCE = 0.02
"""A half turn about a model axis is a symmetry where it moves the model's points onto its surface within this
fraction of the diameter (mean nearest-point distance): LM-O's eggbox and glue about z 0.014 / 0.011, every other
half turn of its objects 0.025 or more."""


def half_turn_symmetries(points: np.ndarray, diameter: float, tolerance: float = FLIP_TOLERANCE) -> list[Symmetry]:
    """The identity and the half turns about the model's x, y and z axes that map its `points` (N,3, m) onto
    themselves: a symmetric object's discrete symmetries from its points alone (a bag carries no models_info),
    so that eval, replay and the jitter share one definition. Continuous symmetries are not found."""
    tree = cKDTree(points)
    out: list[Symmetry] = [(np.eye(3), np.zeros(3))]
    for axis in "xyz":
        R = Rotation.from_euler(axis, 180, degrees=True).as_matrix()
        if tree.query(points @ R.T)[0].mean() < tolerance * diameter:
            out.append((R, np.zeros(3)))
    return out


def equivalent_poses(R_gt: np.ndarray, t_gt: np.ndarray, syms: Sequence[Symmetry]) -> list[tuple[np.ndarray, np.ndarray]]:
    """The GT pose's symmetric equivalents (R_gt S, t_gt + R_gt s); the GT pose itself without symmetries."""
    return [(R_gt @ S, t_gt + R_gt @ s) for S, s in syms] or [(R_gt, t_gt)]


def nearest_truth(R_pred: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, syms: Sequence[Symmetry]) -> tuple[np.ndarray, np.ndarray]:
    """The GT pose among the object's symmetric equivalents nearest the predicted rotation."""
    return min(equivalent_poses(R_gt, t_gt, syms), key=lambda o: re(R_pred, o[0]))


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
    symmetries: Sequence[Symmetry] | None = None,
) -> dict[str, float]:
    """Every error and thresholded success used in reports, keyed as in the eval JSON (add_0.1d, reproj_5px, ...).

    `symmetries` None: an object without symmetry (ADD). Otherwise a symmetric object's equivalent poses (ADD-S;
    the rotation, reprojection and translation errors each minimised over them, as MSSD and MSPD are; the identity
    alone where the sequence is empty): choosing another of its indistinguishable poses is not an error."""
    add_err = add_or_adi(R_est, t_est, R_gt, t_gt, pts, symmetries is not None)
    truths = equivalent_poses(R_gt, t_gt, symmetries or ())
    proj_err = min(proj(R_est, t_est, R, t, K, pts) for R, t in truths)
    scores: dict[str, float] = {"add_err_m": add_err, "reproj_err_px": proj_err}
    for frac in ADD_THRESHOLDS:
        scores[f"add_{frac:g}d"] = float(add_err < frac * diameter)
    for px in REPROJ_THRESHOLDS:
        scores[f"reproj_{px:g}px"] = float(proj_err < px)
    scores["rot_err_deg"] = min(re(R_est, R) for R, _ in truths)
    scores["trans_err_mm"] = 1000.0 * min(te(t_est, t) for _, t in truths)
    return scores


# ------------------------------------------------------------------------------------------ BOP19 errors


def symmetry_transformations(
    discrete: tuple[np.ndarray, ...] | list[np.ndarray], continuous: tuple[dict, ...] | list[dict], max_sym_disc_step: float = 0.01
) -> list[Symmetry]:
    """An object's symmetry transformations [(R, t), ...] (t in metres), the identity first: the discrete ones of
    models_info.json (4x4, translation in metres) and its continuous ones sampled as bop_toolkit's
    `get_symmetry_transformations` does (ceil(pi / max_sym_disc_step) rotations about each axis, composed with
    every discrete one); an axis offset is taken in metres."""
    disc = [(np.eye(3), np.zeros(3))] + [(np.asarray(T, float)[:3, :3], np.asarray(T, float)[:3, 3]) for T in discrete]
    cont = []
    for sym in continuous:
        axis = np.asarray(sym["axis"], float)
        axis = axis / np.linalg.norm(axis)
        offset = np.asarray(sym.get("offset", (0.0, 0.0, 0.0)), float)
        steps = int(np.ceil(np.pi / max_sym_disc_step))
        for R in Rotation.from_rotvec(np.outer(np.arange(steps) * 2.0 * np.pi / steps, axis)).as_matrix():
            cont.append((R, offset - R @ offset))
    if not cont:
        return disc
    return [(Rc @ Rd, Rc @ td + tc) for Rd, td in disc for Rc, tc in cont]


def mssd(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, pts: np.ndarray, syms: list[Symmetry]) -> float:
    """MSSD (BOP19): the largest distance (m) between model points under the estimate and under the GT pose,
    minimised over the object's symmetries `syms` (`symmetry_transformations`)."""
    est = transform(R_est, t_est, pts)
    return min(float(np.linalg.norm(est - transform(R_gt @ Rs, R_gt @ ts + t_gt, pts), axis=1).max()) for Rs, ts in syms)


def mspd(
    R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, K: np.ndarray, pts: np.ndarray, syms: list[Symmetry]
) -> float:
    """MSPD (BOP19): the largest distance (px) between model points projected under the estimate and under the GT
    pose, minimised over the object's symmetries `syms`."""
    est = project(K, transform(R_est, t_est, pts))
    return min(float(np.linalg.norm(est - project(K, transform(R_gt @ Rs, R_gt @ ts + t_gt, pts)), axis=1).max()) for Rs, ts in syms)


def distance_image(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Distance from the camera centre (same unit as `depth`) per pixel of a depth (z) image; 0 stays 0
    (bop_toolkit's `depth_im_to_dist_im`: skew ignored)."""
    h, w = depth.shape
    x = (np.arange(w) - K[0, 2]) / K[0, 0]
    y = (np.arange(h) - K[1, 2]) / K[1, 1]
    return np.asarray(depth, np.float64) * np.sqrt(x[None, :] ** 2 + y[:, None] ** 2 + 1.0)


def vsd(
    depth_est: np.ndarray, depth_gt: np.ndarray, depth_test: np.ndarray, K: np.ndarray, delta: float, taus: Sequence[float], diameter: float
) -> list[float]:
    """VSD (BOP19, step cost, taus relative to the diameter), one error per tau: the share of the object's visible
    surface where the estimate's and the GT's rendered depths (`depth_est`, `depth_gt`; 0 where the model is
    not) disagree. Visibility against the scene's depth `depth_test` with tolerance `delta` (m), a pixel without
    a measurement (0) counting as visible (bop_toolkit's 'bop19' mode)."""
    d_test, d_gt, d_est = (distance_image(d, K) for d in (depth_test, depth_gt, depth_est))
    visib_gt = ((d_gt - d_test <= delta) | (d_test == 0)) & (d_gt > 0)
    visib_est = (((d_est - d_test <= delta) | (d_test == 0)) & (d_est > 0)) | (visib_gt & (d_est > 0))
    inter, union = visib_gt & visib_est, int((visib_gt | visib_est).sum())
    if union == 0:
        return [1.0] * len(taus)
    dists = np.abs(d_gt[inter] - d_est[inter]) / diameter
    outside = union - int(inter.sum())
    return [float((np.count_nonzero(dists >= tau) + outside) / union) for tau in taus]
