"""The poses of rigid objects that may look the same in several poses: 4x4 transforms, a pose's symmetric
equivalents, rotation gaps up to symmetry, and the mean of several views of one object."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from axispose_core.metrics import Symmetry

IDENTITY: tuple[Symmetry, ...] = ((np.eye(3), np.zeros(3)),)


@dataclass(frozen=True)
class ObjectGeometry:
    """What consistency needs of an object: its diameter (m) and its symmetries (the identity first)."""

    diameter: float
    symmetries: tuple[Symmetry, ...] = IDENTITY


def pose_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def inverse(T: np.ndarray) -> np.ndarray:
    return pose_matrix(T[:3, :3].T, -T[:3, :3].T @ T[:3, 3])


def variants(R: np.ndarray, t: np.ndarray, geometry: ObjectGeometry) -> list[np.ndarray]:
    """A pose's symmetric equivalents (R S, t + R s), as 4x4."""
    return [pose_matrix(R @ S, t + R @ s) for S, s in geometry.symmetries]


def rotation_gap_deg(Ra: np.ndarray, Rb: np.ndarray, geometry: ObjectGeometry) -> float:
    """The least angle between two rotations of an object over its symmetries."""
    return min(angle_deg(Ra @ S, Rb) for S, _ in geometry.symmetries)


def angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """The angle between two rotations (degrees)."""
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1.0, 1.0))))


def aligned(T: np.ndarray, reference: np.ndarray, geometry: ObjectGeometry) -> np.ndarray:
    """The symmetric equivalent of pose T nearest `reference` in rotation."""
    return min(variants(T[:3, :3], T[:3, 3], geometry), key=lambda V: angle_deg(V[:3, :3], reference[:3, :3]))


def fuse(poses: Sequence[np.ndarray], information: Sequence[np.ndarray], geometry: ObjectGeometry) -> np.ndarray:
    """One pose from views of an object at rest (4x4, fixed frame): rotations (each the symmetric equivalent nearest
    the first's) by their chordal mean, positions by their information."""
    ref = poses[0]
    turned = [aligned(T, ref, geometry) for T in poses]
    R = Rotation.from_matrix(np.array([T[:3, :3] for T in turned])).mean().as_matrix()
    total = np.sum(information, axis=0)
    t = np.linalg.solve(total, np.einsum("nij,nj->i", np.array(information), np.array([T[:3, 3] for T in poses])))
    return pose_matrix(R, t)
