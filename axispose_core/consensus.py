"""Several sampled poses of one object -> one consensus pose, its spread, and a 6x6 covariance.

The AGM is a sampler: K noise seeds give K axis images and so K poses of the same crop. Where the crop is clear
they agree; where it is ambiguous (occlusion, blur, a view that hides the object's axes) they scatter. The
consensus resists a minority of wrong samples (the medoid sample, then the mean of the samples near it); the
spread is measured over every sample, wrong ones included, so disagreement is reported, not hidden.

The covariance follows geometry_msgs/PoseWithCovariance: order (x, y, z, rotation about X, Y, Z), all in the
camera frame, the rotation part from the rotation vectors of R_i R_cᵀ. It is the mean outer product of the
samples' deviations from the consensus (`scatter`) plus a small floor, so it stays positive definite for any K.

Symmetric objects: samples that differ by one of the object's symmetries count as disagreeing (the object specs
carry a symmetry flag, not the symmetry transforms), so their spread over-states the uncertainty.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

ROT_FLOOR_RAD = float(np.radians(0.5))
"""Least standard deviation per rotation axis in the covariance (the samples share one crop and one reader)."""
TRANS_FLOOR_M = 1e-3
"""Least standard deviation per translation axis in the covariance."""


@dataclass(frozen=True)
class Consensus:
    R: np.ndarray
    t: np.ndarray
    medoid: int
    """Index of the sample closest to all others (its axis image stands for the set)."""
    inliers: np.ndarray
    """(K,) bool: the samples averaged into R, t."""
    spread_deg: float
    """RMS rotation angle of all samples from the consensus."""
    spread_m: float
    """RMS distance of all samples' translations from the consensus."""
    scatter: np.ndarray
    """(6, 6) mean outer product of all samples' deviations, in the order x, y, z, rx, ry, rz (m², rad²)."""

    @property
    def covariance(self) -> np.ndarray:
        """`scatter` plus the floor."""
        return self.scatter + np.diag([TRANS_FLOOR_M**2] * 3 + [ROT_FLOOR_RAD**2] * 3)


def _angles(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Pairwise rotation angles (rad) between two stacks of rotations, (A, B)."""
    cos = (np.einsum("aij,bij->ab", Ra, Rb) - 1.0) * 0.5
    return np.arccos(np.clip(cos, -1.0, 1.0))


def consensus(Rs: np.ndarray, ts: np.ndarray, length: float, inlier_deg: float = 30.0) -> Consensus:
    """Consensus of K >= 1 poses (Rs (K,3,3), ts (K,3) in m) of one object of size `length` (m, e.g. λ_O).

    Samples are compared by rotation angle plus translation distance in object sizes (1 rad ~ one `length`);
    inliers are those within `inlier_deg` and one `length` of the medoid.
    """
    Rs, ts = np.asarray(Rs, dtype=float), np.asarray(ts, dtype=float)
    if Rs.ndim != 3 or Rs.shape[1:] != (3, 3) or ts.shape != (len(Rs), 3) or not len(Rs):
        raise ValueError(f"need K >= 1 rotations (K,3,3) and translations (K,3), got {Rs.shape} and {ts.shape}")
    if not length > 0:
        raise ValueError(f"length must be positive, got {length}")
    ang = _angles(Rs, Rs)
    dist = np.linalg.norm(ts[:, None] - ts[None], axis=2)
    medoid = int(np.argmin((ang + dist / length).sum(axis=1)))
    inliers = (ang[medoid] <= np.radians(inlier_deg)) & (dist[medoid] <= length)
    R = Rotation.from_matrix(Rs[inliers]).mean().as_matrix()
    t = ts[inliers].mean(axis=0)
    dev = np.hstack([ts - t, Rotation.from_matrix(Rs @ R.T).as_rotvec()])
    scatter = dev.T @ dev / len(dev)
    return Consensus(
        R=R,
        t=t,
        medoid=medoid,
        inliers=inliers,
        spread_deg=float(np.degrees(np.sqrt(np.mean(np.sum(dev[:, 3:] ** 2, axis=1))))),
        spread_m=float(np.sqrt(np.mean(np.sum(dev[:, :3] ** 2, axis=1)))),
        scatter=scatter,
    )
