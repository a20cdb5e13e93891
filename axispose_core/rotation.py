"""Rotations from matrices that are almost rotations (noisy annotations, least-squares fits)."""

from __future__ import annotations

import numpy as np


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation closest to M in the Frobenius norm (SVD projection onto SO(3), reflection excluded)."""
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
