"""Random object poses over the LM-O range and the square crops a detector would cut around them.

Shared by the tests, the benchmarks and the keypoint reader's training so that all three see one distribution.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from axispose_core.camera import crop_intrinsics
from axispose_core.lmo import LMO_DISTANCE, LMO_K, LMO_SIZE


@dataclass(frozen=True)
class PatchSample:
    """An object at pose (R, t) seen in a size x size crop whose intrinsics are K_patch."""

    K: np.ndarray
    K_patch: np.ndarray
    R: np.ndarray
    t: np.ndarray
    center: tuple[float, float]
    side: float


def sample_pose(
    rng: np.random.Generator,
    K: np.ndarray = LMO_K,
    image_size: tuple[int, int] = LMO_SIZE,
    distance: tuple[float, float] = LMO_DISTANCE,
    margin: float = 0.1,
) -> tuple[np.ndarray, np.ndarray]:
    """Uniform random rotation; origin at a uniform depth, projecting inside the image less a relative margin."""
    R = Rotation.random(random_state=rng).as_matrix()
    w, h = image_size
    u = rng.uniform(margin * w, (1 - margin) * w)
    v = rng.uniform(margin * h, (1 - margin) * h)
    z = rng.uniform(*distance)
    t = np.linalg.solve(K, np.array([u, v, 1.0])) * z
    return R, t


def sphere_crop(K: np.ndarray, t: np.ndarray, radius: float, pad: float = 1.25) -> tuple[tuple[float, float], float]:
    """Square around the projection of a sphere of `radius` at the object origin, enlarged by `pad`."""
    uvw = K @ t
    center = (float(uvw[0] / uvw[2]), float(uvw[1] / uvw[2]))
    side = 2.0 * radius * 0.5 * (K[0, 0] + K[1, 1]) / t[2] * pad
    return center, side


def sample_patch(
    rng: np.random.Generator,
    radius: float,
    size: int,
    K: np.ndarray = LMO_K,
    pad: tuple[float, float] = (1.2, 1.5),
    center_jitter: float = 0.05,
) -> PatchSample:
    """A random pose and a detector-like crop around it: side jittered by `pad`, centre by a fraction of the side."""
    R, t = sample_pose(rng, K)
    (cx, cy), side = sphere_crop(K, t, radius, rng.uniform(*pad))
    cx += rng.uniform(-center_jitter, center_jitter) * side
    cy += rng.uniform(-center_jitter, center_jitter) * side
    return PatchSample(K, crop_intrinsics(K, (cx, cy), side, size), R, t, (cx, cy), side)
