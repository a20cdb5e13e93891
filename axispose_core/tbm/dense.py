"""The pose from the encoder's dense surface points, with the rotation from the axes and the depth head.

Each visible pixel u of the encoder's surface-point map says which model point X it shows, u ≃ K (R X + t). With
R from the TBM that is linear in t (`translation_from_points`); `fuse_pose` solves R and t together, with the
TBM's rotation and origin and the encoder's depth as priors. No CAD model is needed: the points are the network's,
in λ_O units. The correspondences arrive as `DensePoints`; reading them off the AGM's encoding is the AGM's business
(`agm/correspondences.py`), so the solver depends on nothing upstream of it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from axispose_core.camera import project, projection_jacobian

MIN_POINTS = 8
"""Fewer usable correspondences than this give no translation."""

RAYLEIGH_MEDIAN = float(np.sqrt(2 * np.log(2)))
"""Median length of a 2D residual whose coordinates are N(0, 1)."""

SIGMA_FLOOR_PX = 0.17
"""Least residual scale (px per coordinate) `fuse_pose` assumes for the dense points."""


class DensePoints(NamedTuple):
    """One crop's 2D-3D correspondences, the solver's input: pixels uv (N,2) (pixel centres at integers), model
    points X (N,3) in metres and each point's prior weight (N,), e.g. the mask probability."""

    uv: np.ndarray
    X: np.ndarray
    weight: np.ndarray


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
        w = np.concatenate([prior, prior]) * _robust(np.abs(A @ t - b), k)
        if w.sum() <= 0:
            return None
    return t


def _robust(r: np.ndarray, k: int) -> np.ndarray:
    """IRLS weights of residual magnitudes r at iteration k: Huber for the first three (a start far off must not
    lose its inliers), then Tukey's biweight, both on the residual's MAD scale."""
    scale = 1.4826 * np.median(r) + 1e-12
    if k < 3:
        return np.minimum(1.0, 1.345 * scale / np.maximum(r, 1e-15))
    return np.clip(1 - (r / (4.685 * scale)) ** 2, 0, None) ** 2


@dataclass(frozen=True)
class DenseFusion:
    """How `fuse_pose` weighs the dense points against the TBM's rotation and origin and the encoder's depth:
    Gaussian priors whose widths are those sources' errors, and the points' total weight as a number of independent
    points (the network's point errors are correlated across a crop: hundreds of pixels say about as much as
    ten independent measurements)."""

    points: float = 10.0
    """Effective number of independent points the dense map counts as; 0 leaves the pose as the TBM and the
    depth fusion give it."""
    rotation_sigma: float = 0.1
    """Width of the prior on the rotation, around the TBM's (radians)."""
    depth_sigma: float = 0.02
    """Width of the prior on log depth, around the encoder's depth head."""
    origin_sigma: float = 2.0
    """Width of the prior on where the object's origin projects, around the TBM's (crop pixels): the reader finds
    the drawn origin to a pixel or two, while the visible points' centre moves with occlusion."""
    covariance_scale: tuple[float, float] = (1.0, 1.0)
    """Factors on the variances of the fused pose's translation and rotation: the model above is made to place the
    pose, and on held-out frames its Laplace covariance is narrower than the errors; these make the errors' median
    squared Mahalanobis lengths χ²(3)'s (`axispose eval` reports them as `calibration`)."""

    def __post_init__(self) -> None:
        if len(self.covariance_scale) != 2 or not all(f > 0 for f in self.covariance_scale):
            raise ValueError(f"dense_fusion.covariance_scale must be two positive factors, got {self.covariance_scale}")


class FusedPose(NamedTuple):
    R: np.ndarray
    t: np.ndarray
    covariance: np.ndarray
    """(6, 6) in geometry_msgs/PoseWithCovariance's order (x, y, z, rotation about X, Y, Z; camera frame; m², rad²):
    the inverse of the Gauss-Newton normal matrix at the solution, i.e. the Laplace approximation of the posterior
    that the points (at their measured residual scale and robust weights) and the priors define, its blocks scaled
    by `DenseFusion.covariance_scale`."""


_ROS_ORDER = [3, 4, 5, 0, 1, 2]
"""The solver's state (ω, t) reordered to (t, ω)."""


def fuse_pose(
    K: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    points: DensePoints,
    depth: float,
    fusion: DenseFusion,
    iters: int = 8,
) -> FusedPose | None:
    """The pose most probable given the dense points, the TBM's rotation R and origin (where t projects) and the
    encoder's `depth` (m), from the start (R, t): robust Gauss-Newton (R perturbed on the left, R ← exp([ω]×) R)
    on the `points`' reprojection errors (in units of their robust scale per coordinate; prior weights scaled to sum
    to `fusion.points`, IRLS weights as in `translation_from_points`) with the three priors as further residuals.
    A tilted object's apparent size trades its tilt against its distance; the points see its shape, the head its
    size, the TBM its axes: solving for both together lets each settle what the others leave open. With it, its
    covariance: a crop whose points disagree with each other or with the priors gets a wide one.
    None when fewer than MIN_POINTS have weight, or the pose falls behind the camera."""
    keep = points.weight > 0
    if keep.sum() < MIN_POINTS or t[2] <= 0 or not depth > 0:
        return None
    uv, X, prior = points.uv[keep], points.X[keep], points.weight[keep].astype(np.float64)
    prior *= fusion.points / prior.sum()
    R0, R, t = np.asarray(R, dtype=np.float64), np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)
    origin = project(K, t[None])[0]
    w = prior
    # Small products by einsum, not BLAS: beside PyTorch's threads in the node, OpenBLAS's own thread pool, woken for
    # every product, cost ~10 ms per object.
    for k in range(iters):
        p = np.einsum("nj,ij->ni", X, R) + t
        q = np.einsum("nj,ij->ni", p, K)
        if np.any(q[:, 2] <= 0):
            return None
        proj = q[:, :2] / q[:, 2:3]
        res = proj - uv  # (N,2) px
        r = np.linalg.norm(res, axis=1)
        # px per coordinate, from the median length of the 2D residuals (σ√(2 ln 2) for Gaussian ones); the floor
        # keeps exact points from swamping the priors.
        sigma = max(float(np.median(r)) / RAYLEIGH_MEDIAN, SIGMA_FLOOR_PX)
        if k > 0:
            w = prior * _robust(r, k)
            if w.sum() <= 0:
                return None
        # d proj / d p (N,2,3); through dp/dω = -[R X]x each row a gives a^T (-[R X]x) = (R X) × a, and dp/dt = I.
        dproj = projection_jacobian(K, proj, q[:, 2])
        J = np.concatenate([np.cross((p - t)[:, None, :], dproj), dproj], axis=2).reshape(-1, 6)
        sw = np.repeat(w, 2) / sigma**2
        H = np.einsum("ni,nj->ij", J, J * sw[:, None])
        g = np.einsum("ni,n->i", J, -res.reshape(-1) * sw)
        # Priors: the rotation's offset from the TBM's (its log map; Jacobian ~ I near it), the log depth's and the
        # origin's projection.
        H[:3, :3] += np.eye(3) / fusion.rotation_sigma**2
        g[:3] -= cv2.Rodrigues(R @ R0.T)[0][:, 0] / fusion.rotation_sigma**2
        dz = 1 / (t[2] * fusion.depth_sigma)
        H[5, 5] += dz**2
        g[5] -= dz * np.log(t[2] / depth) / fusion.depth_sigma
        qt = np.einsum("ij,j->i", K, t)
        at = qt[:2] / qt[2]  # where the origin projects now
        Jo = projection_jacobian(K, at[None], qt[2:])[0]  # it moves with t as any point does
        H[3:, 3:] += np.einsum("ki,kj->ij", Jo, Jo) / fusion.origin_sigma**2
        g[3:] -= np.einsum("ki,k->i", Jo, at - origin) / fusion.origin_sigma**2
        step = np.linalg.solve(H, g)
        R = cv2.Rodrigues(step[:3])[0] @ R
        t = t + step[3:]
        if t[2] <= 0:
            return None
        if np.abs(step).max() < 1e-9:
            break
    cov = np.linalg.inv(H)[np.ix_(_ROS_ORDER, _ROS_ORDER)]
    d = np.sqrt(np.repeat(fusion.covariance_scale, 3))
    return FusedPose(R, t, (cov + cov.T) / 2 * np.outer(d, d))
